//! `hgcd validate`: the paper's validation experiment (§5, Fig. 2) on any device, in process.
//!
//! A probe mass m_p rests on a virtual horizontal surface of stiffness k at 27 contact points
//! around the grid centre; at steady state it sinks by ΔX = ‖P_n − X‖, which is m_p g / k when
//! the handle's own weight is compensated exactly and (M(X) + m_p) g / k without compensation.
//! Each point is measured `repetitions` times per compensation mode (none, scalar, vector).
//!
//! The parts: `probe.rs`, the application side (the surface and the moves, tick by tick);
//! `controller.rs`, the probe feeding the daemon's own compensation controller on the servo thread;
//! `report.rs`, the statistics and the table, CSV and JSON; `figure.rs`, Fig. 2 as SVG and PNG.
//! docs/validation.md describes the experiment for users.

pub mod controller;
mod figure;
pub mod probe;
mod report;
pub mod sweep;

use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::Instant;

use nalgebra::Vector3;
use thiserror::Error;
use tracing::info;

pub use crate::figure::{FigureError, OutError};
pub use probe::Reading;
pub use report::{ModeReport, PointStats, Readings, Report, Sample};

use crate::calibrate::{
    calibrate, device_grid, CalibrateError, CalibrateRequest, CalibrationRun, GridModelError,
};
use crate::config::{CompensationMode, Config, ConfigError, DeviceSpec, WorkspaceMode};
use crate::control::calibration::CalibrationEvent;
use crate::control::compensation::{Compensation, ForceOffset, GravityModel};
use crate::grid::GridFile;
use crate::servo::thread::ThreadError;
use crate::servo::{self, ExitReason, Fault, ServoError, ServoOptions, TimingStats};
use crate::sim::SimDevice;
use crate::transport::{self, Pacing, Transport, TransportError};
use controller::ExperimentController;
use probe::{ContactPlan, Probe, ProbeParams, Rest, DITHER_ACROSS};

/// Compensation during one run of the experiment.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Mode {
    /// No gravity compensation: the handle's own apparent weight adds to the probe's.
    None,
    /// The paper's M(X) g v_G.
    Scalar,
    /// The calibrated holding-force vectors, interpolated.
    Vector,
    /// The arm model of a grid calibrated with an arm profile, as its calibration chose it
    /// (with or without the residual lattice).
    Arm,
}

impl Mode {
    pub const ALL: [Mode; 4] = [Mode::None, Mode::Scalar, Mode::Vector, Mode::Arm];

    /// The modes run when none are named: none, scalar and vector, and arm for a device whose
    /// profile has an arm.
    pub fn defaults(has_arm: bool) -> Vec<Mode> {
        let mut modes = vec![Mode::None, Mode::Scalar, Mode::Vector];
        if has_arm {
            modes.push(Mode::Arm);
        }
        modes
    }

    /// The name used on the command line and in the output files.
    pub fn name(self) -> &'static str {
        match self {
            Mode::None => "none",
            Mode::Scalar => "scalar",
            Mode::Vector => "vector",
            Mode::Arm => "arm",
        }
    }

    /// The compensation of this mode with the grid `file`.
    fn compensation(self, file: &GridFile) -> Option<CompensationMode> {
        match self {
            Mode::None => None,
            Mode::Scalar => Some(CompensationMode::Scalar),
            Mode::Vector => Some(CompensationMode::Vector),
            Mode::Arm => Some(
                match file.model.as_ref().and_then(|m| m.chosen.parse().ok()) {
                    Some(CompensationMode::ArmResidual) => CompensationMode::ArmResidual,
                    _ => CompensationMode::Arm,
                },
            ),
        }
    }
}

impl std::str::FromStr for Mode {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        Mode::ALL
            .into_iter()
            .find(|m| m.name() == s)
            .ok_or_else(|| format!("unknown mode `{s}`; use none, scalar, vector or arm"))
    }
}

/// What `hgcd validate` was asked to do. SI units.
#[derive(Clone, Debug)]
pub struct ValidateRequest {
    pub device: DeviceSpec,
    /// Pacing of simulated devices (virtual time for batch work).
    pub pacing: Pacing,
    /// The grid to compensate with; None: the device's stored grid, or on a simulated device a
    /// fresh calibration written to `out`.
    pub grid: Option<PathBuf>,
    /// Directory for the results.
    pub out: PathBuf,
    /// m_p, kg.
    pub probe_mass: f64,
    /// k, N/m.
    pub stiffness: f64,
    pub repetitions: usize,
    /// Runs, in this order.
    pub modes: Vec<Mode>,
    /// Also sweep the grid over this many random reachable points (`sweep.json`; simulated
    /// devices only).
    pub sweep: Option<usize>,
}

/// Probe masses the experiment accepts, kg (1 g to 1 kg).
pub const PROBE_MASS_RANGE: (f64, f64) = (0.001, 1.0);
/// Surface stiffnesses it accepts, N/m (0.05 to 10 N/mm).
pub const STIFFNESS_RANGE: (f64, f64) = (50.0, 10_000.0);
/// Repetitions per point and mode it accepts.
pub const REPETITIONS_RANGE: (usize, usize) = (1, 1000);

/// Why `hgcd validate` did not produce its results.
#[derive(Debug, Error)]
pub enum ValidateError {
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error("--probe-mass-g {} is out of range (1 to 1000 g)", .0 * 1e3)]
    ProbeMass(f64),
    #[error("--stiffness-n-per-mm {} is out of range (0.05 to 10 N/mm)", .0 * 1e-3)]
    Stiffness(f64),
    #[error("--repetitions {0} is out of range (1 to 1000)")]
    Repetitions(usize),
    #[error(
        "validation.dither_hz = {hz} Hz (and 1.51 times that across the surface) needs at least \
         eight reports a period: at most {:.0} Hz at servo.rate_hz = {rate}, or \
         validation.dither_n = 0",
        (rate / 8.0 / DITHER_ACROSS).floor()
    )]
    DitherTooFast { hz: f64, rate: f64 },
    #[error(
        "--modes names no mode, or one twice; give some of none, scalar, vector, arm once each"
    )]
    Modes,
    #[error(transparent)]
    Out(#[from] OutError),
    /// The device cannot be opened (the error names it).
    #[error(transparent)]
    Open(TransportError),
    #[error(transparent)]
    Grid(#[from] GridModelError),
    #[error(
        "contact point ({:.1}, {:.1}, {:.1}) mm lies outside the grid {} or outside \
         device.workspace_*_mm: lower validation.point_spacing_mm or calibrate a larger grid",
        point.x * 1e3, point.y * 1e3, point.z * 1e3, grid.display()
    )]
    PointOutside { point: Vector3<f64>, grid: PathBuf },
    #[error("the calibration before the experiment failed")]
    Calibration(#[source] CalibrateError),
    #[error(transparent)]
    Thread(#[from] ThreadError),
    #[error("the experiment stopped")]
    Servo(#[source] ServoError),
    #[error("the experiment was aborted; no results were written")]
    Aborted,
    #[error("the experiment stopped by a fault: {0}; no results were written")]
    Fault(Fault),
    #[error("the experiment ended early ({0:?}); no results were written")]
    EndedEarly(ExitReason),
    #[error("writing {}", path.display())]
    Write {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error(transparent)]
    Figure(#[from] FigureError),
    #[error(transparent)]
    Sweep(#[from] sweep::SweepError),
}

/// Something to show while the validation runs (on the calling thread).
#[derive(Clone, Copy, Debug)]
pub enum ValidateEvent<'a> {
    /// Progress of the calibration that precedes the experiment on a simulated device.
    Calibration(&'a CalibrationEvent),
    /// The experiment started: `of` repetitions in all.
    Started { of: usize },
    /// A repetition ended: the `done`-th of `of`, in `mode`, with penalty ΔX, m.
    Rest {
        done: usize,
        of: usize,
        mode: Mode,
        penalty: f64,
    },
}

/// Where the grid comes from.
enum GridSource {
    /// A grid file, loaded.
    File(Box<GridFile>, PathBuf),
    /// A fresh calibration of the simulated device, written to this file.
    Calibrate(PathBuf),
}

/// A validation ready to run: the output directory checked, the device open, the grid known.
pub struct Prepared {
    config: Config,
    request: ValidateRequest,
    transport: Box<dyn Transport>,
    grid: GridSource,
    /// The surface's normal where known before the grid ([`surface_normal`]).
    up: Option<Vector3<f64>>,
    /// The device, not the wall clock, sets the loop's pace ([`Pacing::set_by_device`]).
    device_paces: bool,
}

/// The files a validation wrote.
#[derive(Clone, Debug)]
pub struct Outputs {
    pub csv: PathBuf,
    pub summary: PathBuf,
    pub svg: PathBuf,
    pub png: PathBuf,
    /// `sweep.json`, with `--sweep`.
    pub sweep: Option<PathBuf>,
}

/// A finished validation.
#[derive(Debug)]
pub struct Validation {
    pub report: Report,
    pub outputs: Outputs,
    /// The calibration run first, on a simulated device without `--grid`.
    pub calibration: Option<CalibrationRun>,
    /// The grid over random reachable points, with `--sweep`.
    pub sweep: Option<sweep::Sweep>,
    pub stats: TimingStats,
    /// Wall-clock duration of the whole validation (calibration and sweep included), s;
    /// `summary.json`'s `wall_time_s` leaves the sweep out.
    pub wall_time: f64,
}

/// Check the request, make sure the results can be written, open the device and find the grid.
/// Nothing moves yet: on hardware, ask the user to attach the probe mass after this.
pub fn prepare(config: &Config, request: &ValidateRequest) -> Result<Prepared, ValidateError> {
    config.validate()?;
    check_request(request)?;
    let (v, rate) = (&config.validation, config.servo.rate_hz);
    if v.dither_n > 0.0 && DITHER_ACROSS * v.dither_hz > rate / 8.0 {
        return Err(ValidateError::DitherTooFast {
            hz: v.dither_hz,
            rate,
        });
    }
    crate::figure::check_out_dir(&request.out, "validate")?;
    let mut request = request.clone();
    if request.modes.is_empty() {
        let has_arm = crate::profile::Profile::for_device(&request.device, config)
            .is_ok_and(|p| p.gravity_arm().is_some());
        request.modes = Mode::defaults(has_arm);
    }
    let simulated = matches!(request.device, DeviceSpec::Sim { .. });
    // On a simulated device the probe mass is part of the plant, beside any payload its handle
    // carries (`sim.probe_mass_kg`); on hardware the user attaches it.
    let mut device_config = config.clone();
    device_config.sim.probe_mass_kg += request.probe_mass;
    let transport = transport::open(&request.device, &device_config, request.pacing)
        .map_err(ValidateError::Open)?;
    let up = surface_normal(&request.device, &device_config)?;
    let device = transport::identify(transport.as_ref(), &request.device, &device_config)
        .map_err(ValidateError::Open)?;
    request.device = device.spec.clone();
    // What the device says about itself stands in for the workspace keys the config omits.
    let config = &config.for_device(device.info.as_ref());
    let grid = match &request.grid {
        None if simulated => GridSource::Calibrate(request.out.join("grid.toml")),
        given => {
            let (file, path) = device_grid(given.as_deref(), &config.state_dir(), &device)?;
            GridSource::File(Box::new(file), path)
        }
    };
    if let GridSource::File(file, path) = &grid {
        // Refuse now rather than after the device has moved.
        experiment_setup(config, &request, up, file, path)?;
    }
    let device_paces = request.pacing.set_by_device(&device);
    Ok(Prepared {
        config: config.clone(),
        request,
        transport,
        grid,
        up,
        device_paces,
    })
}

/// The surface's normal, "up" (opposite to gravity) in the device frame, where the config or the
/// device knows it: `validation.up_direction`, else on a simulated device its world's up. None
/// leaves it to the grid's v_G (the paper's assumption: the handle's apparent gravity force is
/// vertical).
fn surface_normal(
    device: &DeviceSpec,
    config: &Config,
) -> Result<Option<Vector3<f64>>, ValidateError> {
    if let Some(up) = config.validation.up_direction {
        return Ok(Some(Vector3::from(up).normalize()));
    }
    match device {
        DeviceSpec::Sim { model } => {
            let sim = SimDevice::from_config(model, config).map_err(|source| {
                ValidateError::Open(TransportError::Simulation {
                    spec: device.to_string(),
                    source,
                })
            })?;
            Ok(Some(sim.plant().up()))
        }
        _ => Ok(None),
    }
}

fn check_request(r: &ValidateRequest) -> Result<(), ValidateError> {
    let within = |v: f64, (lo, hi): (f64, f64)| v >= lo && v <= hi;
    if !within(r.probe_mass, PROBE_MASS_RANGE) {
        return Err(ValidateError::ProbeMass(r.probe_mass));
    }
    if !within(r.stiffness, STIFFNESS_RANGE) {
        return Err(ValidateError::Stiffness(r.stiffness));
    }
    if r.repetitions < REPETITIONS_RANGE.0 || r.repetitions > REPETITIONS_RANGE.1 {
        return Err(ValidateError::Repetitions(r.repetitions));
    }
    let mut modes = r.modes.clone();
    modes.sort();
    modes.dedup();
    if modes.len() != r.modes.len() {
        return Err(ValidateError::Modes);
    }
    if let Some(n) = r.sweep {
        if !matches!(r.device, DeviceSpec::Sim { .. }) {
            return Err(sweep::SweepError::NotSimulated.into());
        }
        if n < sweep::POINTS_RANGE.0 || n > sweep::POINTS_RANGE.1 {
            return Err(sweep::SweepError::Points(n).into());
        }
    }
    Ok(())
}

/// What the experiment needs from a grid.
struct Setup {
    plan: ContactPlan,
    params: ProbeParams,
    /// The gravity model of each run (None: uncompensated).
    models: Vec<Option<Box<GravityModel>>>,
}

/// The contact plan, the probe's parameters and the model of each run, for `file`.
fn experiment_setup(
    config: &Config,
    request: &ValidateRequest,
    up: Option<Vector3<f64>>,
    file: &GridFile,
    path: &Path,
) -> Result<Setup, ValidateError> {
    let grid = &file.grid;
    let v = &config.validation;
    let centre = (grid.origin + grid.far_corner()) / 2.0;
    let plan = ContactPlan::paper(
        centre,
        v.point_spacing(),
        up.unwrap_or(grid.gravity_direction),
        request.modes.len(),
        request.repetitions,
    );
    let (lo, hi) = config.device.workspace();
    for p in &plan.points {
        let lifted = p + plan.normal * v.lift();
        let dropped = p - plan.normal * v.drop();
        let inside = |x: &Vector3<f64>| (0..3).all(|a| x[a] >= lo[a] && x[a] <= hi[a]);
        if !grid.contains(p) || !inside(p) || !inside(&lifted) || !inside(&dropped) {
            return Err(ValidateError::PointOutside {
                point: *p,
                grid: path.to_path_buf(),
            });
        }
    }
    let params = ProbeParams::configured(config, request.stiffness);
    let models = request
        .modes
        .iter()
        .map(|mode| match mode.compensation(file) {
            None => Ok(None),
            Some(m) => GravityModel::new(file.clone(), m, config.compensation.outside_grid)
                .map(|model| Some(Box::new(model)))
                .map_err(GridModelError::model(path)),
        })
        .collect::<Result<Vec<_>, _>>()?;
    Ok(Setup {
        plan,
        params,
        models,
    })
}

impl Prepared {
    /// The device the validation runs on (with the serial number a HID device reported).
    pub fn device(&self) -> &DeviceSpec {
        &self.request.device
    }

    /// Whether a fresh calibration runs first.
    pub fn calibrates_first(&self) -> bool {
        matches!(self.grid, GridSource::Calibrate(_))
    }

    /// Calibrate first if needed, run the experiment, write the results. `progress` sees every
    /// event on the calling thread.
    pub fn run(
        self,
        stop: Arc<AtomicBool>,
        progress: &mut dyn FnMut(ValidateEvent),
    ) -> Result<Validation, ValidateError> {
        let started = Instant::now();
        let Prepared {
            config,
            request,
            transport,
            grid,
            up,
            device_paces,
        } = self;
        let calibrates = matches!(grid, GridSource::Calibrate(_));
        let (file, path, calibration) = match grid {
            GridSource::File(file, path) => (*file, path, None),
            GridSource::Calibrate(path) => {
                let run = calibrate_simulated(&config, &request, &path, stop.clone(), progress)?;
                (run.grid.clone(), path, Some(run))
            }
        };
        // The sweep sets the paper's cube and the explored grid side by side: calibrate the
        // one the config did not ask for as well.
        let other = match (request.sweep, calibrates) {
            (Some(_), true) => {
                let mut config = config.clone();
                let name = match config.calibration.workspace {
                    WorkspaceMode::Cube => {
                        config.calibration.workspace = WorkspaceMode::Explore;
                        "explored-grid.toml"
                    }
                    WorkspaceMode::Explore => {
                        config.calibration.workspace = WorkspaceMode::Cube;
                        "cube-grid.toml"
                    }
                };
                let path = request.out.join(name);
                let run = calibrate_simulated(&config, &request, &path, stop.clone(), progress)?;
                Some((run.grid, path))
            }
            _ => None,
        };
        let Setup {
            plan,
            params,
            models,
        } = experiment_setup(&config, &request, up, &file, &path)?;
        let points = plan.points.clone();
        let normal = plan.normal;
        let total = plan.total();
        progress(ValidateEvent::Started { of: total });
        info!(
            "validating {} with the grid {}: {} points × {} repetitions × {} modes",
            request.device,
            path.display(),
            points.len(),
            request.repetitions,
            request.modes.len()
        );

        let (tx, rx) = crossbeam_channel::bounded(4096);
        let compensation = Compensation::new(
            None,
            ForceOffset::new(config.app.stale_offset(), config.app.stale_ramp()),
        );
        let controller =
            ExperimentController::new(compensation, models, Probe::new(plan, params), Some(tx));
        let mut options = ServoOptions::from_config(&config);
        options.stop_on_fault = true;
        let mut done = 0;
        let mut above = None;
        // A repetition ends with its reading from below; show its two-sided penalty.
        let mut show = |rest: Rest, done: &mut usize| match rest.reading {
            Reading::Below => {
                *done += 1;
                let x = above
                    .take()
                    .map_or(rest.position, |a: Vector3<f64>| (a + rest.position) / 2.0);
                progress(ValidateEvent::Rest {
                    done: *done,
                    of: total,
                    mode: request.modes[rest.run],
                    penalty: (points[rest.point] - x).norm(),
                });
            }
            _ => above = Some(rest.position),
        };
        let (result, controller) = servo::thread::run_watched(
            transport,
            controller,
            options,
            config.servo.clone(),
            device_paces,
            stop,
            &mut || rx.try_iter().for_each(|rest| show(rest, &mut done)),
        )?;
        let servo_report = result.map_err(ValidateError::Servo)?;
        match servo_report.exit {
            ExitReason::ControllerDone => {}
            ExitReason::Stopped => return Err(ValidateError::Aborted),
            ExitReason::Fault(fault) => return Err(ValidateError::Fault(fault)),
            exit => return Err(ValidateError::EndedEarly(exit)),
        }
        let report = Report::new(
            &request,
            &file,
            &path,
            &points,
            &normal,
            (
                config.validation.dither_n,
                config.validation.dither_hz,
                config.validation.dither_s,
            ),
            &controller.into_rests(),
        );
        let mut outputs = write_outputs(&request.out, &report, started.elapsed().as_secs_f64())?;
        let mut swept = None;
        if let (Some(n), DeviceSpec::Sim { model }) = (request.sweep, &request.device) {
            let sweepable = |file: &GridFile, path: &Path| -> Result<_, ValidateError> {
                let model = GravityModel::configured(
                    file.clone(),
                    config.compensation.mode,
                    config.compensation.outside_grid,
                )
                .map_err(GridModelError::model(path))?;
                Ok(sweep::SweptGrid::new(model, file))
            };
            let mut cube = None;
            let mut explored = None;
            for (file, path) in
                std::iter::once((&file, &path)).chain(other.iter().map(|(f, p)| (f, p)))
            {
                let slot = if file.explored() {
                    &mut explored
                } else {
                    &mut cube
                };
                *slot = Some(sweepable(file, path)?);
            }
            let sweep = sweep::Sweep::run(
                model,
                &config,
                cube.as_ref(),
                explored.as_ref(),
                n,
                config.sim.seed,
            )?;
            let target = request.out.join("sweep.json");
            std::fs::write(&target, sweep.json()).map_err(|source| ValidateError::Write {
                path: target.clone(),
                source,
            })?;
            outputs.sweep = Some(target);
            swept = Some(sweep);
        }
        Ok(Validation {
            report,
            outputs,
            calibration,
            sweep: swept,
            stats: servo_report.stats,
            wall_time: started.elapsed().as_secs_f64(),
        })
    }
}

/// Calibrate the simulated device (without the probe mass; with the payload its config gives
/// the handle) into `path`.
fn calibrate_simulated(
    config: &Config,
    request: &ValidateRequest,
    path: &Path,
    stop: Arc<AtomicBool>,
    progress: &mut dyn FnMut(ValidateEvent),
) -> Result<CalibrationRun, ValidateError> {
    let calibrate_request = CalibrateRequest {
        device: request.device.clone(),
        pacing: request.pacing,
        output: Some(path.to_path_buf()),
        state_dir: config.state_dir(),
    };
    calibrate(config, &calibrate_request, stop, &mut |e| {
        progress(ValidateEvent::Calibration(e))
    })
    .map_err(ValidateError::Calibration)
}

/// Write the CSV, summary.json and the figure into `out`.
fn write_outputs(out: &Path, report: &Report, wall_time: f64) -> Result<Outputs, ValidateError> {
    let outputs = Outputs {
        csv: out.join("penalties.csv"),
        summary: out.join("summary.json"),
        svg: out.join("penalty.svg"),
        png: out.join("penalty.png"),
        sweep: None,
    };
    let write = |path: &Path, text: String| {
        std::fs::write(path, text).map_err(|source| ValidateError::Write {
            path: path.to_path_buf(),
            source,
        })
    };
    write(&outputs.csv, report.csv())?;
    write(&outputs.summary, report.summary_json(wall_time))?;
    figure::draw(report, &outputs.svg, &outputs.png)?;
    Ok(outputs)
}
