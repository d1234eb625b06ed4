//! `hgcd calibrate`: run Algorithm 1 on a device inside the servo loop and persist the grid.

pub mod check;
pub mod persist;

use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::Instant;

use thiserror::Error;
use tracing::{info, warn};

use crate::config::{Config, ConfigError, DeviceSpec, WorkspaceMode};
use crate::control::calibration::{
    Calibration, CalibrationEvent, CalibrationFailure, CalibrationParams, CalibrationResult,
    PlanError, VertexResult,
};
use crate::control::compensation::ModelError;
use crate::grid::{grid_path, DeviceIdentity, GridError, GridFile};
use crate::servo::thread::ThreadError;
use crate::servo::{self, ExitReason, Fault, ServoError, ServoOptions, TimingStats};
use crate::transport::{self, Pacing, Transport, TransportError};
use persist::{check_room, grid_file};

/// A calibration rides out a silent device (the watchdog zeroes the force, then the vertex in
/// progress goes on) for this many watchdog periods; a longer silence ends it.
pub const SILENCE_LIMIT_WATCHDOGS: f64 = 10.0;

/// Why `hgcd calibrate` wrote nothing.
#[derive(Debug, Error)]
pub enum CalibrateError {
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// The device cannot be opened, or hgcd cannot run it (the error names it).
    #[error(transparent)]
    Open(TransportError),
    #[error(transparent)]
    Plan(#[from] PlanError),
    /// The output directory is unusable or has no room for the grid (checked before starting).
    #[error(transparent)]
    NoRoom(GridError),
    #[error(transparent)]
    Thread(#[from] ThreadError),
    #[error("calibration stopped; nothing was written")]
    Servo(#[source] ServoError),
    #[error("calibration failed: {0}; nothing was written")]
    Failed(CalibrationFailure),
    #[error("calibration aborted; nothing was written")]
    Aborted,
    #[error("calibration stopped by a fault: {0}; nothing was written")]
    Fault(Fault),
    #[error("calibration ended early ({0:?}); nothing was written")]
    EndedEarly(ExitReason),
    #[error(transparent)]
    Save(GridError),
}

/// Why a command that compensates with a calibrated grid (`hgcd record`, `hgcd validate`,
/// `hgcd analyze`) has no gravity model from it.
#[derive(Debug, Error)]
pub enum GridModelError {
    #[error(
        "no calibration grid for {device} at {}: calibrate it first (`hgcd calibrate --device \
         {device}`) or pass --grid FILE",
        path.display()
    )]
    NoGrid { device: String, path: PathBuf },
    #[error(transparent)]
    Grid(GridError),
    #[error("grid {}: {source}", path.display())]
    Model {
        path: PathBuf,
        #[source]
        source: ModelError,
    },
}

impl GridModelError {
    /// [`GridModelError::Model`] for the grid at `path`.
    pub fn model(path: &Path) -> impl FnOnce(ModelError) -> Self + '_ {
        |source| Self::Model {
            path: path.to_path_buf(),
            source,
        }
    }
}

/// The grid file `given`, or without one the grid calibration stored for `device` under
/// `state_dir`, with its path.
///
/// Errors: [`GridModelError::NoGrid`] when no grid is stored for `device` (a missing `given` file
/// is [`GridModelError::Grid`], as is every other error [`GridFile::load_for`] returns).
pub fn device_grid(
    given: Option<&Path>,
    state_dir: &Path,
    device: &DeviceIdentity,
) -> Result<(GridFile, PathBuf), GridModelError> {
    let path = match given {
        Some(path) => path.to_path_buf(),
        None => grid_path(state_dir, &device.grid_id()),
    };
    match GridFile::load_for(&path, device) {
        Ok(file) => Ok((file, path)),
        Err(GridError::Missing { .. }) if given.is_none() => Err(GridModelError::NoGrid {
            device: device.spec.to_string(),
            path,
        }),
        Err(e) => Err(GridModelError::Grid(e)),
    }
}

/// What `hgcd calibrate` was asked to do.
#[derive(Clone, Debug)]
pub struct CalibrateRequest {
    pub device: DeviceSpec,
    /// Pacing of simulated devices (virtual time for batch work).
    pub pacing: Pacing,
    /// Where to write the grid: this file, or `<state_dir>/<grid id>.toml` (the id is the
    /// device's model and serial number when it names itself, see `grid::DeviceIdentity`).
    pub output: Option<PathBuf>,
    pub state_dir: PathBuf,
}

/// Vertices whose pace [`TimeLeft`] takes for the rest's.
const RECENT_VERTICES: usize = 3;

/// A duration for people: "45 s", "3 min 05 s".
fn duration_for_people(seconds: f64) -> String {
    let s = seconds.max(0.0).round() as u64;
    if s < 60 {
        format!("{s} s")
    } else {
        format!("{} min {:02} s", s / 60, s % 60)
    }
}

/// The device time a calibration has left, from its events, for the progress display and the
/// daemon's replies alike: the pace of the last `RECENT_VERTICES` vertices for each still to
/// come. Its base is the first vertex's start (after the initialisation and any exploring,
/// which say nothing about the vertices' pace). The recent pace, not the whole run's: the first
/// vertices, measured with rests and bands, take two to three times as long as those predicted
/// from them. On the simulated PHANToM with every vertex held at 0.04 N, after the ninth vertex
/// the run's mean said 1 min 30 s were left, the recent pace says 57 s: 18 vertices of a
/// stroke and a move each, 3.15 s.
#[derive(Clone, Copy, Debug, Default)]
pub struct TimeLeft {
    /// How many vertices were done, and the device time, at the end of each of the last
    /// [`RECENT_VERTICES`] vertices (the first vertex's start counting as 0 done), newest last.
    recent: [Option<(usize, f64)>; RECENT_VERTICES],
}

impl TimeLeft {
    /// Takes in one event; after a vertex is done or skipped, "about … of device time left".
    pub fn update(&mut self, event: &CalibrationEvent) -> Option<String> {
        let (vertex, of, elapsed) = match *event {
            CalibrationEvent::VertexStarted {
                vertex: 0, elapsed, ..
            } => {
                if self.recent.iter().all(Option::is_none) {
                    self.recent[RECENT_VERTICES - 1] = Some((0, elapsed));
                }
                return None;
            }
            CalibrationEvent::VertexDone {
                vertex,
                of,
                elapsed,
                ..
            }
            | CalibrationEvent::VertexUnreachable {
                vertex,
                of,
                elapsed,
                ..
            } => (vertex, of, elapsed),
            _ => return None,
        };
        // None before the first vertex's start.
        let (done, since) = self.recent.iter().flatten().next().copied()?;
        self.recent.rotate_left(1);
        self.recent[RECENT_VERTICES - 1] = Some((vertex + 1, elapsed));
        let pace = (elapsed - since) / (vertex + 1).saturating_sub(done).max(1) as f64;
        let left = pace * of.saturating_sub(vertex + 1) as f64;
        Some(format!(
            "about {} of device time left",
            duration_for_people(left)
        ))
    }
}

/// A finished, saved calibration.
#[derive(Clone, Debug)]
pub struct CalibrationRun {
    pub result: CalibrationResult,
    pub grid: GridFile,
    pub path: PathBuf,
    pub stats: TimingStats,
    /// Wall-clock duration, s.
    pub wall_time: f64,
}

/// Run the calibration on the device and save the grid atomically. `progress` sees every event
/// (on the calling thread). Nothing is written unless the calibration finishes; every
/// [`CalibrateError`] means nothing was.
pub fn calibrate(
    config: &Config,
    request: &CalibrateRequest,
    stop: Arc<AtomicBool>,
    progress: &mut dyn FnMut(&CalibrationEvent),
) -> Result<CalibrationRun, CalibrateError> {
    config.validate()?;
    let transport =
        transport::open(&request.device, config, request.pacing).map_err(CalibrateError::Open)?;
    calibrate_on(transport, config, request, stop, progress)
}

/// [`calibrate`] on the device `request.device` names, already opened as `transport`.
///
/// What the device says about itself (its device-info report) names the grid and stands in for
/// the workspace and calibration-cube keys the config file does not give
/// ([`Config::for_device`]). A watchdog fault zeroes the force; the calibration then goes on with
/// the vertex it was on when reports resume within [`SILENCE_LIMIT_WATCHDOGS`] watchdog periods,
/// and ends otherwise.
pub fn calibrate_on(
    transport: Box<dyn Transport>,
    config: &Config,
    request: &CalibrateRequest,
    stop: Arc<AtomicBool>,
    progress: &mut dyn FnMut(&CalibrationEvent),
) -> Result<CalibrationRun, CalibrateError> {
    config.validate()?;
    let (device, config) = identified(transport.as_ref(), &request.device, config)?;
    let config = &config;
    let path = match &request.output {
        Some(path) => path.clone(),
        None => grid_path(&request.state_dir, &device.grid_id()),
    };
    let params = CalibrationParams::for_device(config, &request.device);
    let (tx, rx) = crossbeam_channel::bounded(4096);
    let calibration = Calibration::new(params, Some(tx))?;
    let plan = calibration.plan();
    // Fail now rather than after minutes of calibration.
    check_room(&path, plan, &device.spec).map_err(CalibrateError::NoRoom)?;
    if !plan.left_out.is_empty() {
        let names: Vec<String> = plan.left_out.iter().map(|v| v.to_string()).collect();
        warn!(
            "{} vertices lie outside the workspace (device.workspace_*_mm) and are left out; the \
             grid shrinks to {}×{}×{}: {}",
            plan.left_out.len(),
            plan.dims[0],
            plan.dims[1],
            plan.dims[2],
            names.join("; ")
        );
    }
    let c = &config.calibration;
    match c.workspace {
        WorkspaceMode::Cube => info!(
            "calibrating {} vertices ({}×{}×{}, {} mm apart around ({}, {}, {}) mm) on {device}",
            plan.path.len(),
            plan.dims[0],
            plan.dims[1],
            plan.dims[2],
            c.spacing_mm,
            c.centre_mm[0],
            c.centre_mm[1],
            c.centre_mm[2],
        ),
        WorkspaceMode::Explore => info!(
            "exploring the workspace of {device} on a {} mm lattice from ({}, {}, {}) mm, then \
             calibrating the vertices the handle reaches (docs/calibration.md §12)",
            c.spacing_mm, c.centre_mm[0], c.centre_mm[1], c.centre_mm[2],
        ),
    }
    let started = Instant::now();
    let (result, stats) = drive(
        transport,
        (calibration, rx),
        config,
        request.pacing.set_by_device(&device),
        stop,
        progress,
    )?;
    let (stops, unread): (Vec<&VertexResult>, Vec<&VertexResult>) = result
        .vertices
        .iter()
        .filter(|v| result.unreachable.contains(&v.vertex))
        .partition(|v| v.failure.is_none());
    // A cube's missed vertices were approached again from beside them; an explored workspace's
    // map already knew where the handle goes, and they were not.
    let sides = if result.workspace.is_some() {
        ""
    } else {
        ", from two sides"
    };
    if !stops.is_empty() {
        let names: Vec<String> = stops.iter().map(|v| v.vertex.to_string()).collect();
        warn!(
            "{} of {} vertices could not be reached (the handle did not yield to a push toward \
             them{sides}) and were filled from their neighbours: {}",
            names.len(),
            result.vertices.len(),
            names.join("; ")
        );
    }
    if !unread.is_empty() {
        let names: Vec<String> = unread
            .iter()
            .filter_map(|v| v.failure.map(|f| f.to_string()))
            .collect();
        warn!(
            "{} of {} vertices could not be measured{sides}, and were filled from their \
             neighbours: {}",
            names.len(),
            result.vertices.len(),
            names.join("; ")
        );
    }
    let mut grid = grid_file(&result, config, &device.spec);
    device.stamp(&mut grid);
    grid.save_atomic(&path).map_err(CalibrateError::Save)?;
    info!("grid written to {}", path.display());
    Ok(CalibrationRun {
        result,
        grid,
        path,
        stats,
        wall_time: started.elapsed().as_secs_f64(),
    })
}

/// The device behind `transport` (opened as `spec`), and `config` with what it says of itself
/// standing in for the keys the file did not give ([`Config::for_device`]).
pub(crate) fn identified(
    transport: &dyn Transport,
    spec: &DeviceSpec,
    config: &Config,
) -> Result<(DeviceIdentity, Config), CalibrateError> {
    let device = transport::identify(transport, spec, config).map_err(CalibrateError::Open)?;
    let config = config.for_device(device.info.as_ref());
    Ok((device, config))
}

/// Drive `calibration` (and the receiver of its events, handed to `progress` on this thread)
/// on `transport` to its end on the servo thread, as every calibration runs: a fault ends it,
/// a silence of up to [`SILENCE_LIMIT_WATCHDOGS`] watchdog periods is ridden out. Its result
/// and the loop's statistics; nothing is saved.
pub(crate) fn drive(
    transport: Box<dyn Transport>,
    (calibration, events): (Calibration, crossbeam_channel::Receiver<CalibrationEvent>),
    config: &Config,
    device_paced: bool,
    stop: Arc<AtomicBool>,
    progress: &mut dyn FnMut(&CalibrationEvent),
) -> Result<(CalibrationResult, TimingStats), CalibrateError> {
    let mut options = ServoOptions::from_config(config);
    options.stop_on_fault = true;
    options.silence_limit = SILENCE_LIMIT_WATCHDOGS * options.watchdog;
    // The controller (holding the sender) comes back when the run ends, so watch the thread
    // rather than wait for the channel to close.
    let (result, calibration) = servo::thread::run_watched(
        transport,
        calibration,
        options,
        config.servo.clone(),
        device_paced,
        stop,
        &mut || events.try_iter().for_each(|event| progress(&event)),
    )?;
    let report = result.map_err(CalibrateError::Servo)?;
    match (report.exit, calibration.outcome()) {
        (_, Some(Ok(result))) => Ok((result, report.stats)),
        (_, Some(Err(failure))) => Err(CalibrateError::Failed(failure)),
        (ExitReason::Stopped, None) => Err(CalibrateError::Aborted),
        (ExitReason::Fault(fault), None) => Err(CalibrateError::Fault(fault)),
        (exit, None) => Err(CalibrateError::EndedEarly(exit)),
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::Vector3;

    use super::*;
    use crate::control::calibration::Vertex;

    #[test]
    fn the_time_left_is_the_recent_vertices_pace_times_the_vertices_to_come() {
        assert_eq!(duration_for_people(44.6), "45 s");
        assert_eq!(duration_for_people(185.0), "3 min 05 s");
        let mut left = TimeLeft::default();
        let at = Vertex {
            index: [0; 3],
            position: Vector3::zeros(),
        };
        let done = |vertex, elapsed| CalibrationEvent::VertexDone {
            vertex,
            of: 27,
            mass: 0.0,
            force: Vector3::zeros(),
            iterations: 1,
            elapsed,
        };
        assert_eq!(
            left.update(&done(0, 20.0)),
            None,
            "no base before the first vertex"
        );
        let started = CalibrationEvent::VertexStarted {
            vertex: 0,
            of: 27,
            at,
            elapsed: 10.0,
        };
        assert_eq!(left.update(&started), None);
        // The first vertex in 20 s: 20 s each for the 26 to come.
        assert_eq!(
            left.update(&done(0, 30.0)).as_deref(),
            Some("about 8 min 40 s of device time left")
        );
        // Three vertices in 30 s, the first one's start still among the last three: 10 s each
        // for the 24 to come.
        left.update(&done(1, 35.0));
        assert_eq!(
            left.update(&done(2, 40.0)).as_deref(),
            Some("about 4 min 00 s of device time left")
        );
        // Then faster: the pace of the last three, 4 s each (52 s − 40 s), for the 21 to come.
        for (vertex, elapsed) in [(3, 44.0), (4, 48.0)] {
            left.update(&done(vertex, elapsed));
        }
        assert_eq!(
            left.update(&done(5, 52.0)).as_deref(),
            Some("about 1 min 24 s of device time left")
        );
        assert_eq!(
            left.update(&done(26, 130.0)).as_deref(),
            Some("about 0 s of device time left")
        );
    }
}
