//! `hgcd check`: is the saved gravity model still right? Two friction-robust holds, at the ends
//! of the calibrated cube's main diagonal (measured as calibration measures a vertex, after its
//! initialisation), are compared with the model, and what differs is explained, if it can be,
//! by a payload added to the handle and a tilt of the base (docs/calibration.md §2.1).
//!
//! The two explanations are the model's own: [`GravityModel::with_effect_bounded`] adds a
//! payload's weight along the model's v_G and turns the field (a lattice) or the gravity the arm
//! is held against (an arm model), as `hgcd run` compensates them. Three unknowns (the
//! payload's mass, the tilt about the two axes across v_G; a turn about v_G itself changes no
//! force) from six equations, by Levenberg–Marquardt from zero: the three left over tell a
//! payload and a tilt from anything else (a spring, a cable, another arm).

use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use nalgebra::{Matrix3, Rotation3, SMatrix, Vector3};
use thiserror::Error;
use tracing::info;

use super::{device_grid, drive, identified, CalibrateError, GridModelError};
use crate::config::{Config, DeviceSpec};
use crate::control::calibration::{
    Calibration, CalibrationEvent, CalibrationParams, CalibrationResult, Holds, Prior,
};
use crate::control::compensation::{GravityModel, StaticEffect};
use crate::grid::{
    restore_backup, AppliedRecord, Change, ChangeError, DeviceIdentity, GridError, GridFile,
};
use crate::transport::{self, Pacing};

pub use crate::app::protocol::{Check, Hold, Reverted, Verdict};

/// A hold agrees with the model when they differ by at most this share of the model's force
/// there, or [`TOLERANCE_MIN`], whichever is larger: twice the calibration's own accuracy
/// (0.5 % at its worst vertex, docs/calibration.md §7.1).
pub const TOLERANCE_SHARE: f64 = 0.01;
/// N: a few times the noise of a hold on the simulated linkages (0.4–0.6 mN).
pub const TOLERANCE_MIN: f64 = 0.002;

/// What a payload and a tilt may leave of a hold's difference from the model and still explain
/// it: this share of the difference (or the hold's tolerance). A tilt turns the gravity that
/// parameters act against which an upright calibration could not see (a counterweight along a
/// vertical joint axis): the arm model predicts a tilted field only to a few millinewtons.
pub const EXPLAINED_SHARE: f64 = 0.2;
/// Beyond these the fit explains nothing: a tilt of more than 30° or a payload of more than
/// 1 kg is not what a changed handle or table gives (rad, kg).
const MAX_TILT: f64 = 0.52;
const MAX_PAYLOAD: f64 = 1.0;

/// Levenberg–Marquardt iterations and the finite-difference steps of its Jacobian (kg, rad).
const ITERATIONS: usize = 50;
const MASS_STEP: f64 = 1e-5;
const ANGLE_STEP: f64 = 1e-5;

/// What `hgcd check` was asked to do.
#[derive(Clone, Debug)]
pub struct CheckRequest {
    pub device: DeviceSpec,
    pub pacing: Pacing,
    /// The grid to check: this file, or the one calibration stored for the device.
    pub grid: Option<PathBuf>,
    pub state_dir: PathBuf,
}

impl Verdict {
    /// The exit status `hgcd check` ends with (docs/calibration.md §2).
    pub fn exit_code(self) -> u8 {
        match self {
            Verdict::Unchanged => 0,
            Verdict::Apply => 4,
            Verdict::Recalibrate => 5,
        }
    }
}

impl Check {
    /// The change found, as `--apply` takes it in.
    pub fn change(&self) -> Change {
        Change {
            payload_kg: self.payload_g * 1e-3,
            tilt: Vector3::from(self.tilt_axis) * self.tilt_deg.to_radians(),
        }
    }
}

/// A serial arm's base moments act only under a tilted base, so a calibration on a level one
/// cannot measure them: it leaves them out (docs/calibration.md §13.2), and one under a slight
/// tilt measures them poorly. Where the change tilts the arm's base further than it was when
/// they were fitted, the applied model misses whatever base moments the arm has, most beyond the
/// calibrated cube (docs/calibration.md §2.2): say so.
fn base_moments_warning(before: &GridFile, after: &GridFile) -> Option<String> {
    let (was, now) = (before.arm.as_ref()?, after.arm.as_ref()?);
    let names = now.gravity().ok()?.arm.parameter_names();
    let base = names.iter().any(|n| n.starts_with("base"));
    let left_out = was.unidentified.iter().any(|n| n.starts_with("base"));
    (base && now.tilt_deg >= 1.0 && now.tilt_deg > was.tilt_deg).then(|| {
        let measured = if left_out {
            "could not be measured then and are taken as nil"
        } else {
            "were measured under less tilt"
        };
        format!(
            "the arm's base now leans {:.1}° (it leaned {:.1}° at its calibration): its base \
             moments, which act only when it leans, {measured}, so if the arm has any the applied \
             model misses them, most beyond the calibrated cube; hgcd calibrate measures them",
            now.tilt_deg, was.tilt_deg
        )
    })
}

/// Why a check has no answer.
#[derive(Debug, Error)]
pub enum CheckError {
    #[error(transparent)]
    Grid(#[from] GridModelError),
    #[error("check: {0}")]
    Measure(#[from] CalibrateError),
    #[error("check: a hold was not measured ({0}); nothing to compare")]
    NoHold(String),
    #[error("check --apply: {}: {source}", path.display())]
    Apply {
        path: PathBuf,
        #[source]
        source: ChangeError,
    },
    #[error("check --apply: {0}")]
    Save(GridError),
    #[error(
        "check --revert: nothing kept beside {}: no model was replaced there (by --apply or a \
         calibration)",
        path.display()
    )]
    NothingKept { path: PathBuf },
}

/// Measure the two holds on the device and compare them with its saved model. `progress` sees
/// the calibration events of the measurement. Nothing is written.
pub fn check(
    config: &Config,
    request: &CheckRequest,
    stop: Arc<AtomicBool>,
    progress: &mut dyn FnMut(&CalibrationEvent),
) -> Result<Check, CheckError> {
    config.validate().map_err(CalibrateError::from)?;
    let transport =
        transport::open(&request.device, config, request.pacing).map_err(CalibrateError::Open)?;
    let (device, config) = identified(transport.as_ref(), &request.device, config)?;
    let config = &config;
    let (file, path) = device_grid(request.grid.as_deref(), &request.state_dir, &device)?;
    let planned = plan(config, &request.device, file, path)?;
    let (tx, rx) = crossbeam_channel::bounded(4096);
    let calibration =
        Calibration::new(planned.params.clone(), Some(tx)).map_err(CalibrateError::from)?;
    let (result, _) = drive(
        transport,
        (calibration, rx),
        config,
        request.pacing.set_by_device(&device),
        stop,
        progress,
    )?;
    planned.conclude(&result)
}

/// What a check measures against, and how: the saved model, and the calibration parameters
/// that hold the two ends of the main diagonal of the largest cube its grid holds about its
/// centre. `hgcd check` and the daemon's `check` request both start here.
pub struct Planned {
    pub model: GravityModel,
    /// m/s², the grid's.
    pub g: f64,
    pub params: CalibrationParams,
    /// The grid file checked.
    pub grid: PathBuf,
}

/// The check of `file` (read from `path`) on `device`.
///
/// # Errors
/// [`CheckError::Grid`] where the grid's model cannot be built.
pub fn plan(
    config: &Config,
    device: &DeviceSpec,
    file: GridFile,
    path: PathBuf,
) -> Result<Planned, CheckError> {
    let c = &config.compensation;
    let g = file.grid.g;
    let grid = file.grid.clone();
    let record = file.calibration.clone().unwrap_or_default();
    let model = GravityModel::configured(file, c.mode, c.outside_grid)
        .map_err(GridModelError::model(&path))?;
    // Half the smallest side, in cells (a 2-vertex side: half a cell).
    let half_cells = grid.dims.iter().map(|&n| n - 1).min().unwrap_or(0) as f64 / 2.0;
    let mut params = CalibrationParams::for_device(config, device);
    params.holds = Holds::Diagonal;
    // The calibration measured the friction and moving mass at this centre: the check starts
    // its holds once the handle is caught.
    params.prior = match Prior::from_record(&record, params.max_force) {
        Ok(prior) => Some(Prior {
            model: Some(model.clone()),
            ..prior
        }),
        Err(why) => {
            info!(
                "{} cannot shorten the check's initialisation: {why}; measuring the friction \
                 and moving mass again",
                path.display()
            );
            None
        }
    };
    params.half_size = 1;
    params.spacing = grid.spacing * half_cells;
    params.centre = grid.origin
        + Vector3::new(
            grid.dims[0] as f64 - 1.0,
            grid.dims[1] as f64 - 1.0,
            grid.dims[2] as f64 - 1.0,
        ) * (grid.spacing / 2.0);
    let (lo, hi) = (
        (params.centre.add_scalar(-params.spacing)) * 1e3,
        (params.centre.add_scalar(params.spacing)) * 1e3,
    );
    info!(
        "checking {device} against {}: holds at ({:.1}, {:.1}, {:.1}) and ({:.1}, {:.1}, {:.1}) mm",
        path.display(),
        lo.x,
        lo.y,
        lo.z,
        hi.x,
        hi.y,
        hi.z,
    );
    Ok(Planned {
        model,
        g,
        params,
        grid: path,
    })
}

impl Planned {
    /// The answer, from the finished calibration of the two holds.
    ///
    /// # Errors
    /// [`CheckError::NoHold`] where a hold was not measured.
    pub fn conclude(&self, result: &CalibrationResult) -> Result<Check, CheckError> {
        let holds = holds_of(result)?;
        let mut check = compare(&self.model, self.g, &holds);
        check.device_time_s = result.duration;
        check.grid = self.grid.clone();
        Ok(check)
    }
}

/// `hgcd check --apply`: take the change `found` (verdict [`Verdict::Apply`]) into the grid it
/// was measured against, atomically, keeping the model before it as `<grid>.bak`
/// (docs/calibration.md §2.2). Sets `found.applied` to the backup's path.
///
/// # Errors
/// [`CheckError::Apply`] where the grid cannot take the change (the arm model cannot carry a
/// payload at its handle, a result out of range), [`CheckError::Save`] where it cannot be read
/// again or written; the grid is then as it was.
pub fn apply(found: &mut Check) -> Result<(), CheckError> {
    let path = &found.grid;
    let file = GridFile::load(path).map_err(CheckError::Save)?;
    let record = AppliedRecord {
        at: humantime::format_rfc3339_seconds(std::time::SystemTime::now())
            .to_string()
            .parse()
            .ok(),
        hgcd_version: Some(env!("CARGO_PKG_VERSION").to_string()),
        payload_g: found.payload_g,
        tilt_deg: found.tilt_deg,
        tilt_axis: found.tilt_axis,
        device_time_s: Some(found.device_time_s),
    };
    let changed = file
        .with_change(&found.change(), record)
        .map_err(|source| CheckError::Apply {
            path: path.clone(),
            source,
        })?;
    found.warning = base_moments_warning(&file, &changed);
    changed.save_atomic(path).map_err(CheckError::Save)?;
    info!(
        "took a payload of {:+.1} g and a tilt of {:.2}° into {}",
        found.payload_g,
        found.tilt_deg,
        path.display()
    );
    found.applied = Some(backup_of(path));
    Ok(())
}

/// Where [`GridFile::save_atomic`] keeps the file it replaced.
fn backup_of(path: &Path) -> PathBuf {
    let mut name = path.file_name().unwrap_or_default().to_os_string();
    name.push(".bak");
    path.with_file_name(name)
}

/// `hgcd check --revert`: put back the model kept beside the device's grid (or `request.grid`),
/// the one the last `--apply` or calibration replaced; the replaced one is kept in its turn, so
/// a second revert undoes the first. The device is opened to tell which grid is its own;
/// nothing is measured.
///
/// # Errors
/// [`CheckError::NothingKept`] where no model was kept; [`CheckError::Grid`] where either file is
/// not a grid of this device; [`CheckError::Measure`] where the device cannot be opened.
pub fn revert(config: &Config, request: &CheckRequest) -> Result<Reverted, CheckError> {
    config.validate().map_err(CalibrateError::from)?;
    let transport =
        transport::open(&request.device, config, request.pacing).map_err(CalibrateError::Open)?;
    let (device, _) = identified(transport.as_ref(), &request.device, config)?;
    drop(transport);
    revert_grid(request.grid.as_deref(), &request.state_dir, &device)
}

fn revert_grid(
    grid: Option<&Path>,
    state_dir: &Path,
    device: &DeviceIdentity,
) -> Result<Reverted, CheckError> {
    let (current, path) = device_grid(grid, state_dir, device)?;
    revert_file(current, path, device)
}

/// `hgcd check --revert --via-daemon`: the daemon puts back the model kept beside its grid
/// `path`, of its `device`, before it compensates with it.
///
/// # Errors
/// As [`revert`], but for opening the device (the daemon has it open).
pub fn revert_at(path: &Path, device: &DeviceIdentity) -> Result<Reverted, CheckError> {
    let current = GridFile::load_for(path, device).map_err(GridModelError::Grid)?;
    revert_file(current, path.to_path_buf(), device)
}

fn revert_file(
    current: GridFile,
    path: PathBuf,
    device: &DeviceIdentity,
) -> Result<Reverted, CheckError> {
    let kept = backup_of(&path);
    let previous = match GridFile::load_for(&kept, device) {
        Err(GridError::Missing { .. }) => return Err(CheckError::NothingKept { path }),
        other => other.map_err(GridModelError::Grid)?,
    };
    restore_backup(&path).map_err(CheckError::Save)?;
    info!("put back the model kept as {}", kept.display());
    Ok(Reverted {
        grid: path,
        applied_now: previous.applied,
        applied_before: current.applied,
    })
}

/// A measured hold: where (m), and the force that held the handle there (N).
pub type Measured = (Vector3<f64>, Vector3<f64>);

/// The holds a check's run measured.
fn holds_of(result: &CalibrationResult) -> Result<Vec<Measured>, CheckError> {
    result
        .vertices
        .iter()
        .filter(|v| !result.extrapolated.contains(&v.vertex))
        .map(|v| {
            if v.reached && !result.unreachable.contains(&v.vertex) {
                Ok((v.measured_at, v.held_force))
            } else {
                Err(CheckError::NoHold(match v.failure {
                    Some(failure) => failure.to_string(),
                    None => format!("the handle could not reach {}", v.vertex),
                }))
            }
        })
        .collect()
}

/// The payload (kg) and tilt (rotation vector, rad) of `p`, across `up`.
fn effect(p: &Vector3<f64>, across: &[Vector3<f64>; 2], up: &Vector3<f64>, g: f64) -> StaticEffect {
    StaticEffect {
        tilt: Rotation3::new(across[0] * p[1] + across[1] * p[2]),
        weight: up * (p[0] * g),
        spring: None,
        bound: f64::INFINITY,
    }
}

/// Compare `holds` (where, measured force) with `model` (its grid's `g`): the verdict, and the
/// payload and tilt that explain the difference. Device time and grid are left for the caller.
pub fn compare(model: &GravityModel, g: f64, holds: &[Measured]) -> Check {
    let up = model.up;
    let (a, b) = crate::fit::across(&up);
    let across = [a, b];
    let predicted = |p: &Vector3<f64>| -> Vec<Vector3<f64>> {
        let turned = model
            .clone()
            .with_effect_bounded(Some(effect(p, &across, &up, g)), f64::INFINITY);
        holds.iter().map(|(x, _)| turned.force(x)).collect()
    };
    let residual = |p: &Vector3<f64>| -> SMatrix<f64, 6, 1> {
        let mut r = SMatrix::<f64, 6, 1>::zeros();
        for (i, (f, (_, measured))) in predicted(p).iter().zip(holds).enumerate().take(2) {
            r.fixed_rows_mut::<3>(3 * i).copy_from(&(measured - f));
        }
        r
    };
    // Levenberg–Marquardt from no change: the step is damped until it lowers the residual.
    let mut p = Vector3::zeros();
    let mut r = residual(&p);
    let mut damping = 1e-3;
    for _ in 0..ITERATIONS {
        let mut jacobian = SMatrix::<f64, 6, 3>::zeros();
        for k in 0..3 {
            let step = if k == 0 { MASS_STEP } else { ANGLE_STEP };
            let mut dp = Vector3::zeros();
            dp[k] = step;
            let column = (residual(&(p + dp)) - residual(&(p - dp))) / (2.0 * step);
            jacobian.set_column(k, &column);
        }
        let normal: Matrix3<f64> = jacobian.transpose() * jacobian;
        let gradient = jacobian.transpose() * r;
        let mut improved = false;
        while damping < 1e12 {
            let damped = normal + Matrix3::from_diagonal(&normal.diagonal()) * damping;
            let Some(step) = damped.try_inverse().map(|n| -(n * gradient)) else {
                break;
            };
            let next = residual(&(p + step));
            if next.norm_squared() < r.norm_squared() {
                p += step;
                r = next;
                damping = (damping / 10.0).max(1e-9);
                improved = step[0].abs() > 1e-7 || step[1].abs().max(step[2].abs()) > 1e-8;
                break;
            }
            damping *= 10.0;
        }
        if !improved {
            break;
        }
    }
    let before = predicted(&Vector3::zeros());
    let after = predicted(&p);
    let holds: Vec<Hold> = holds
        .iter()
        .zip(before.iter().zip(&after))
        .map(|((x, measured), (model_force, explained))| Hold {
            position_m: (*x).into(),
            measured_n: (*measured).into(),
            model_n: (*model_force).into(),
            unexplained_n: (measured - explained).norm(),
            tolerance_n: (TOLERANCE_SHARE * model_force.norm()).max(TOLERANCE_MIN),
        })
        .collect();
    let agrees = holds
        .iter()
        .zip(&before)
        .all(|(h, f)| (Vector3::from(h.measured_n) - f).norm() <= h.tolerance_n);
    let plausible = p[0].abs() <= MAX_PAYLOAD && p[1].hypot(p[2]) <= MAX_TILT;
    let explained = plausible
        && holds.iter().zip(&before).all(|(h, f)| {
            let difference = (Vector3::from(h.measured_n) - f).norm();
            h.unexplained_n <= h.tolerance_n.max(EXPLAINED_SHARE * difference)
        });
    let verdict = match (agrees, explained) {
        (true, _) => Verdict::Unchanged,
        (false, true) => Verdict::Apply,
        (false, false) => Verdict::Recalibrate,
    };
    let tilt = across[0] * p[1] + across[1] * p[2];
    let angle = tilt.norm();
    Check {
        verdict,
        payload_g: p[0] * 1e3,
        tilt_deg: angle.to_degrees(),
        tilt_axis: if angle > 0.0 {
            (tilt / angle).into()
        } else {
            across[0].into()
        },
        holds,
        device_time_s: 0.0,
        grid: PathBuf::new(),
        applied: None,
        warning: None,
    }
}
