//! Where the model and the measurement disagree (docs/discrepancy.md): `hgcd record` logs an
//! identification run with compensation on ([`record()`]); `hgcd analyze` compares the log with
//! the calibrated model, locates the disagreement, names the physical effects the model is
//! missing (a set, possibly empty), adds them, shows on held-out data that the gap shrinks and
//! says what is left unexplained and what the log could not show ([`analyze`]).

pub mod analysis;
pub mod effects;
pub mod evidence;
pub mod log;
pub mod record;
mod report;

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use thiserror::Error;
use tracing::{info, warn};

use crate::calibrate::{device_grid, GridModelError};
use crate::config::{Config, ConfigError, DeviceSpec};
use crate::control::compensation::GravityModel;
use crate::figure::{FigureError, OutError};
use crate::grid::GridFile;
use crate::servo::thread::ThreadError;
use crate::servo::{self, ExitReason, ServoError, ServoOptions};
use crate::transport::{self, Pacing, TransportError};
use analysis::{Fit, Signals, Step};
pub use effects::Effect;
use evidence::{Limit, NoiseFloor};
use log::{Log, LogError};
use record::{RecordParams, Recorder};
pub use report::{names, Diagnostics};

/// What `hgcd record` is asked to do.
#[derive(Clone, Debug)]
pub struct RecordRequest {
    pub device: DeviceSpec,
    pub pacing: Pacing,
    /// The grid compensating during the run (None: the device's stored grid).
    pub grid: Option<PathBuf>,
    /// The log to write.
    pub out: PathBuf,
    /// Device time to record, s.
    pub duration: f64,
}

/// Why `hgcd record` wrote no log.
#[derive(Debug, Error)]
pub enum RecordError {
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error("--duration {0} s is out of range (10 to 3600 s)")]
    Duration(f64),
    #[error(
        "--duration {duration} s at {rate} Hz gives more than the {} rows hgcd analyze reads: \
         record at most {most} s",
        log::MAX_ROWS
    )]
    TooLong { duration: f64, rate: f64, most: f64 },
    #[error(transparent)]
    Open(TransportError),
    #[error(transparent)]
    Grid(#[from] GridModelError),
    #[error(transparent)]
    Thread(#[from] ThreadError),
    #[error("the recording stopped")]
    Servo(#[source] ServoError),
    #[error("the recording stopped by a fault: {0:?}; no log was written")]
    Ended(ExitReason),
    #[error(transparent)]
    Log(#[from] LogError),
    #[error(
        "{} is already there: hgcd record writes a new log and replaces nothing (a grid, another \
         log); choose another --out",
        .0.display()
    )]
    OutExists(PathBuf),
    #[error(
        "the excitation's loop stayed unstable with its softest gains (K = {} N/m, D = {} N·s/m): \
         the safety layer limited the command on {:.0} % of the last {} s; the run stopped with \
         zero force and no log was written: the device's loop delay (or a very light handle) is \
         beyond what hgcd record excites (docs/discrepancy.md §1)",
        .0.stiffness,
        .0.damping,
        .1 * 1e2,
        record::LIMIT_WINDOW
    )]
    Unstable(log::Excitation, f64),
    #[error(
        "the recording stopped before it logged a row{}; no log was written",
        if *.0 {
            " (the excitation had softened and was holding the handle before it started again)"
        } else {
            ""
        }
    )]
    NothingRecorded(bool),
}

/// A finished recording.
#[derive(Debug)]
pub struct Recording {
    pub log: Log,
    /// Stopped early by Ctrl-C (the log is valid, only shorter).
    pub interrupted: bool,
    /// Each time the excitation's loop went unstable and the run started again with softer
    /// gains (docs/discrepancy.md §1); the log holds the last run only.
    pub softenings: Vec<record::Softening>,
}

/// Drive the device through the excitation (compensation on) and write the log. `progress` sees
/// the share done (0 to 1) now and then, on the calling thread.
///
/// # Errors
/// [`RecordError`]: a bad duration or config, a device that cannot be opened, no usable grid, a
/// fault during the run, an excitation whose loop stayed unstable at its softest gains, or a stop
/// before the first row (no log is written then).
pub fn record(
    config: &Config,
    request: &RecordRequest,
    stop: Arc<AtomicBool>,
    progress: &mut dyn FnMut(f64),
) -> Result<Recording, RecordError> {
    config.validate()?;
    if !(log::MIN_DURATION..=3600.0).contains(&request.duration) {
        return Err(RecordError::Duration(request.duration));
    }
    // Before the device moves: the log goes to a new file only (`Log::save` makes sure of it
    // at the end too, should one appear meanwhile).
    if std::fs::symlink_metadata(&request.out).is_ok() {
        return Err(RecordError::OutExists(request.out.clone()));
    }
    let transport =
        transport::open(&request.device, config, request.pacing).map_err(RecordError::Open)?;
    let device = transport::identify(transport.as_ref(), &request.device, config)
        .map_err(RecordError::Open)?;
    let config = &config.for_device(device.info.as_ref());
    let most = log::MAX_ROWS as f64 * config.servo_period();
    if request.duration > most {
        return Err(RecordError::TooLong {
            duration: request.duration,
            rate: 1.0 / config.servo_period(),
            most,
        });
    }
    let (file, path) = device_grid(request.grid.as_deref(), &config.state_dir(), &device)?;
    let c = &config.compensation;
    let model = GravityModel::configured(file, c.mode, c.outside_grid)
        .map_err(GridModelError::model(&path))?;
    let params = RecordParams::inside(&model, request.duration);
    let recorder = Recorder::new(params, model, config.servo_period());
    let elapsed_ms = recorder.elapsed_ms();
    let mut options = ServoOptions::from_config(config);
    options.stop_on_fault = true;
    info!(
        "recording {} s on {} ({})",
        request.duration,
        device.spec,
        request.out.display()
    );
    let (result, recorder) = servo::thread::run_watched(
        transport,
        recorder,
        options,
        config.servo.clone(),
        request.pacing.set_by_device(&device),
        stop,
        &mut || progress(elapsed_ms.load(Ordering::Relaxed) as f64 * 1e-3 / request.duration),
    )?;
    let report = result.map_err(RecordError::Servo)?;
    let interrupted = match report.exit {
        ExitReason::ControllerDone => false,
        ExitReason::Stopped => true,
        exit => return Err(RecordError::Ended(exit)),
    };
    let softenings: Vec<record::Softening> = recorder.softenings().copied().collect();
    for s in &softenings {
        warn!(
            "the excitation's loop went unstable {:.1} s after the run started: the safety layer \
             limited {:.0} % of the last {} s of commands (K = {} N/m, D = {} N·s/m); recording \
             again from the start with K = {} N/m, D = {} N·s/m",
            s.at,
            s.limited_share * 1e2,
            record::LIMIT_WINDOW,
            s.from.stiffness,
            s.from.damping,
            s.to.stiffness,
            s.to.damping
        );
    }
    if let Some(share) = recorder.unstable() {
        return Err(RecordError::Unstable(recorder.excitation(), share));
    }
    let excitation = recorder.excitation();
    let log = record::log_of(&recorder.into_rows(), device.grid_id(), excitation);
    if log.is_empty() {
        return Err(RecordError::NothingRecorded(!softenings.is_empty()));
    }
    log.save(&request.out)?;
    Ok(Recording {
        log,
        interrupted,
        softenings,
    })
}

/// What `hgcd analyze` is asked to do.
#[derive(Clone, Debug)]
pub struct AnalyzeRequest {
    pub grid: PathBuf,
    pub log: PathBuf,
    pub out: PathBuf,
}

/// Why `hgcd analyze` wrote no report.
#[derive(Debug, Error)]
pub enum AnalyzeError {
    #[error(transparent)]
    Log(#[from] LogError),
    #[error(transparent)]
    Grid(#[from] GridModelError),
    #[error(
        "the grid {} was calibrated on {grid_device} and the log {} recorded on {log_device}: \
         analyse a log with the grid of the same device",
        grid.display(), log.display()
    )]
    ForeignGrid {
        grid: PathBuf,
        log: PathBuf,
        grid_device: String,
        log_device: String,
    },
    #[error(
        "log {}: {share:.0} % of its positions lie outside the grid {}: record inside the \
         calibrated grid (hgcd record does)",
        log.display(), grid.display()
    )]
    OutsideGrid {
        log: PathBuf,
        grid: PathBuf,
        share: f64,
    },
    #[error(
        "log {}: the motion does not excite the model (the handle hardly moved): record with \
         hgcd record",
        .0.display()
    )]
    NoExcitation(PathBuf),
    #[error(
        "log {}: the fitted {why}; no model written: a log that gives such a value holds a \
         fault (a stuck sensor, a force the device never rendered)",
        log.display()
    )]
    AbsurdParameter { why: String, log: PathBuf },
    #[error(transparent)]
    Out(#[from] OutError),
    #[error(transparent)]
    Figure(#[from] FigureError),
}

/// A log whose handle moves slower than this, RMS, excites no model, m/s.
const MIN_RMS_SPEED: f64 = 1e-3;

/// Share of a log's positions that may lie outside the grid.
const MAX_OUTSIDE_SHARE: f64 = 0.05;

/// A finished analysis.
#[derive(Debug)]
pub struct Analysis {
    /// The effects named, in the order found (empty when the model explains the log).
    pub effects: Vec<Effect>,
    pub nominal: Fit,
    /// Every candidate tried alone, in [`Effect::CANDIDATES`] order.
    pub candidates: Vec<Fit>,
    /// The selection's steps: each effect added and the joint fit then.
    pub steps: Vec<Step>,
    /// The augmented model: the named effects fitted jointly (the nominal one when nothing is
    /// named).
    pub augmented: Fit,
    /// The log's own noise floor, and whether the augmented model's held-out residual stays
    /// above it by more than [`evidence::UNEXPLAINED_FACTOR`].
    pub noise_floor: NoiseFloor,
    pub unexplained: bool,
    /// Where the augmented model's held-out residual lives.
    pub ordering: evidence::Ordering,
    /// What the log could not show.
    pub limits: Vec<Limit>,
    /// Held-out RMS position error of the closed-loop simulation, nominal and augmented, m
    /// (logs with a reference and the excitation's gains).
    pub position_error: Option<(f64, f64)>,
    pub diagnostics: Diagnostics,
    /// The grid's v_G.
    pub up: nalgebra::Vector3<f64>,
    /// Wall time, s.
    pub wall_time: f64,
}

impl Analysis {
    /// The first effect named, or [`Effect::None`] (summary.json's `effect`).
    pub fn effect(&self) -> Effect {
        self.effects.first().copied().unwrap_or(Effect::None)
    }

    /// Held-out RMS force residual of the nominal and the augmented model, N.
    pub fn errors(&self) -> (f64, f64) {
        (self.nominal.heldout_error, self.augmented.heldout_error)
    }
}

/// Analyse `request.log` against the grid `request.grid` and write the report in
/// `request.out`. `progress` hears a line per stage.
///
/// # Errors
/// [`AnalyzeError`]: a bad log (docs/log-format.md), a grid that does not load or belongs to
/// another device, a log outside the grid or without motion, or an output that cannot be written.
pub fn analyze(
    request: &AnalyzeRequest,
    progress: &mut dyn FnMut(&str),
) -> Result<Analysis, AnalyzeError> {
    let started = std::time::Instant::now();
    progress("reading the log and the grid");
    let log = Log::load(&request.log)?;
    let file = GridFile::load(&request.grid).map_err(GridModelError::Grid)?;
    if let (Some(grid_device), Some(log_device)) = (file.device.as_ref(), log.device.as_ref()) {
        if &grid_device.id != log_device {
            return Err(AnalyzeError::ForeignGrid {
                grid: request.grid.clone(),
                log: request.log.clone(),
                grid_device: grid_device.id.clone(),
                log_device: log_device.clone(),
            });
        }
    }
    let outside = crate::config::Config::default().compensation.outside_grid;
    let model = GravityModel::configured(file.clone(), None, outside)
        .map_err(GridModelError::model(&request.grid))?;
    let outside = log
        .position
        .iter()
        .filter(|x| !model.grid.contains(x))
        .count() as f64
        / log.len() as f64;
    if outside > MAX_OUTSIDE_SHARE {
        return Err(AnalyzeError::OutsideGrid {
            log: request.log.clone(),
            grid: request.grid.clone(),
            share: outside * 1e2,
        });
    }
    crate::figure::check_out_dir(&request.out, "analyze")?;

    progress("smoothing and differentiating the position");
    // A grid with an arm model gives the arm: the nominal model is then the arm's.
    let arm = file.arm.as_ref().and_then(|a| a.geometry.arm().ok());
    let mut signals = Signals::new(&log, &model, arm.as_ref());
    let speed = (signals
        .samples
        .iter()
        .map(|s| s.velocity.norm_squared())
        .sum::<f64>()
        / signals.len() as f64)
        .sqrt();
    if speed < MIN_RMS_SPEED {
        return Err(AnalyzeError::NoExcitation(request.log.clone()));
    }
    progress("fitting the nominal model (grid and moving mass)");
    let nominal = analysis::nominal(&mut signals)
        .ok_or_else(|| AnalyzeError::NoExcitation(request.log.clone()))?;
    let mut limits = evidence::excitation_limits(&signals);
    // An effect the excitation cannot show alone is not tried; one it cannot tell from another
    // is tried, and the limit says so.
    let candidates: Vec<Effect> = Effect::CANDIDATES
        .into_iter()
        .filter(|e| {
            !limits
                .iter()
                .any(|l| l.effects.len() == 1 && l.effects[0] == *e)
        })
        .collect();
    progress(&format!(
        "selecting effects from {}",
        candidates
            .iter()
            .map(|e| e.name())
            .collect::<Vec<_>>()
            .join(", ")
    ));
    // The floor with the nominal model's inertia guides the selection; the augmented model's is
    // reported.
    let floor = evidence::noise_floor(&log, &signals, &nominal).force;
    let (augmented, steps, first) = analysis::select(&nominal, &signals, &candidates, floor);
    let effects = augmented.effects.clone();
    if augmented.has(Effect::TimeDelay) {
        limits.push(evidence::delay_side());
    }
    limits.push(evidence::below_floor(floor));
    for (effect, with) in analysis::confounded(&augmented, &signals, &candidates) {
        limits.push(evidence::confounded(effect, &with));
    }
    progress("estimating the noise floor");
    let residual = augmented.residuals(&signals);
    let noise_floor = evidence::noise_floor(&log, &signals, &augmented);
    let unexplained = augmented.heldout_error > evidence::UNEXPLAINED_FACTOR * noise_floor.force;
    let ordering = evidence::ordering(&signals, &residual, signals.split().1);
    progress("locating the disagreement and simulating");
    let diagnostics = Diagnostics::new(&signals, &nominal, &augmented, &model);
    // The closed-loop simulation integrates a point mass: not for an arm.
    let excitation = log.excitation.as_ref().filter(|_| !signals.arm);
    let position_error = excitation.and_then(|e| {
        let (_, heldout) = signals.split();
        let error = |fit: &Fit| {
            let simulated = analysis::simulate(&log, &signals, fit, &model, e)?;
            let residual: Vec<_> = (0..signals.len())
                .map(|k| log.position[k + signals.first] - simulated[k + signals.first])
                .collect();
            Some(analysis::rms(&residual, heldout.clone()))
        };
        Some((error(&nominal)?, error(&augmented)?))
    });
    let analysis = Analysis {
        effects,
        nominal,
        candidates: first,
        steps,
        augmented,
        noise_floor,
        unexplained,
        ordering,
        limits,
        position_error,
        diagnostics,
        up: model.up,
        wall_time: started.elapsed().as_secs_f64(),
    };
    progress("writing the report");
    report::write(request, &file, &signals, &analysis)?;
    Ok(analysis)
}
