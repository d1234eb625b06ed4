//! `hgcd calibrate`: run Algorithm 1 on a device inside the servo loop and persist the grid.

use std::path::PathBuf;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::Instant;

use thiserror::Error;
use tracing::{info, warn};

use crate::config::{Config, ConfigError, DeviceSpec};
use crate::control::calibration::persist::{check_room, grid_file};
use crate::control::calibration::{
    Calibration, CalibrationEvent, CalibrationFailure, CalibrationParams, CalibrationResult,
    PlanError,
};
use crate::grid::{grid_path, GridError, GridFile};
use crate::servo::{self, ExitReason, Fault, ServoError, ServoOptions, TimingStats};
use crate::transport::{self, Pacing, TransportError};

/// Why `hgcd calibrate` wrote nothing.
#[derive(Debug, Error)]
pub enum CalibrateError {
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// The device cannot be opened (the error names it).
    #[error(transparent)]
    Open(TransportError),
    #[error(transparent)]
    Plan(#[from] PlanError),
    /// The output directory is unusable or has no room for the grid (checked before starting).
    #[error(transparent)]
    NoRoom(GridError),
    #[error("starting the servo thread")]
    Spawn(#[source] std::io::Error),
    #[error("the servo thread panicked")]
    ServoPanicked,
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

/// What `hgcd calibrate` was asked to do.
#[derive(Clone, Debug)]
pub struct CalibrateRequest {
    pub device: DeviceSpec,
    /// Pacing of simulated devices (virtual time for batch work).
    pub pacing: Pacing,
    /// Where to write the grid: this file, or `<state_dir>/<device-id>.toml`.
    pub output: Option<PathBuf>,
    pub state_dir: PathBuf,
}

impl CalibrateRequest {
    /// The file the grid goes to.
    pub fn output_path(&self) -> PathBuf {
        self.output
            .clone()
            .unwrap_or_else(|| grid_path(&self.state_dir, &self.device.device_id()))
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
    // Name the grid after the device actually opened (a HID serial number the spec left out).
    let mut request = request.clone();
    if let Some(spec) = transport.resolved_spec() {
        request.device = spec;
    }
    let request = &request;
    let path = request.output_path();
    let params = CalibrationParams::from_config(config);
    let (tx, rx) = crossbeam_channel::bounded(4096);
    let calibration = Calibration::new(params, Some(tx))?;
    let plan = calibration.plan();
    // Fail now rather than after minutes of calibration.
    check_room(&path, plan, &request.device).map_err(CalibrateError::NoRoom)?;
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
    info!(
        "calibrating {} vertices ({}×{}×{}) on {}",
        plan.path.len(),
        plan.dims[0],
        plan.dims[1],
        plan.dims[2],
        request.device
    );
    let mut options = ServoOptions::from_config(config);
    options.stop_on_fault = true;
    let mut servo_config = config.servo.clone();
    if request.pacing == Pacing::Virtual && matches!(request.device, DeviceSpec::Sim { .. }) {
        // A virtual-time loop runs flat out: never let it take a core at real-time priority.
        servo_config.realtime_priority = 0;
    }
    let started = Instant::now();
    let handle = servo::thread::spawn(transport, calibration, options, servo_config, stop, None)
        .map_err(CalibrateError::Spawn)?;
    // The controller (holding the sender) comes back through the join handle, so watch the thread
    // rather than wait for the channel to close.
    while !handle.is_finished() {
        for event in rx.try_iter() {
            progress(&event);
        }
        std::thread::sleep(servo::thread::POLL);
    }
    let (result, calibration) = handle.join().map_err(|_| CalibrateError::ServoPanicked)?;
    for event in rx.try_iter() {
        progress(&event);
    }
    let report = result.map_err(CalibrateError::Servo)?;
    let result = match (report.exit, calibration.outcome()) {
        (_, Some(Ok(result))) => result,
        (_, Some(Err(failure))) => return Err(CalibrateError::Failed(failure)),
        (ExitReason::Stopped, None) => return Err(CalibrateError::Aborted),
        (ExitReason::Fault(fault), None) => return Err(CalibrateError::Fault(fault)),
        (exit, None) => return Err(CalibrateError::EndedEarly(exit)),
    };
    if !result.unreachable.is_empty() {
        let names: Vec<String> = result.unreachable.iter().map(|v| v.to_string()).collect();
        warn!(
            "{} of {} vertices could not be reached (the handle did not yield to a push toward \
             them) and were filled from their neighbours: {}",
            names.len(),
            result.vertices.len(),
            names.join("; ")
        );
    }
    let grid = grid_file(&result, config, &request.device);
    grid.save_atomic(&path).map_err(CalibrateError::Save)?;
    info!("grid written to {}", path.display());
    Ok(CalibrationRun {
        result,
        grid,
        path,
        stats: report.stats,
        wall_time: started.elapsed().as_secs_f64(),
    })
}
