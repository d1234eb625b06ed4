//! What a calibration leaves on disk: the grid file built from its result, with the gravity
//! model chosen from its holds (`fit`), and the check, made before it starts, that the file will
//! fit where it goes. Used by `hgcd calibrate` and by the daemon's calibration on request alike.

use std::path::Path;
use std::time::SystemTime;

use tracing::warn;

use crate::config::{CompensationMode, Config, DeviceSpec};
use crate::control::calibration::{CalibrationResult, GridPlan};
use crate::fit::{self, Hold, LatticeHolds};
use crate::grid::{
    self, ArmRecord, CalibrationRecord, DeviceRecord, GridError, GridFile, HeldOutRecord, MassGrid,
    ModelRecord, VertexRecords,
};
use crate::profile::Profile;

/// The record of the device a grid is made for.
fn device_record(device: &DeviceSpec) -> DeviceRecord {
    DeviceRecord {
        id: device.device_id(),
        spec: Some(device.to_string()),
        model: None,
        serial: None,
    }
}

/// Check that the directory of `path` exists (creating it) and has room for the grid `plan` will
/// produce on `device` (see [`grid::check_room`]).
pub fn check_room(path: &Path, plan: &GridPlan, device: &DeviceSpec) -> Result<(), GridError> {
    let vertices = plan.most_vertices();
    // The arm model's tables: under 2 KiB with the longest warning.
    let bytes = GridFile::size_bound(vertices, device.to_string().len()) + 2048;
    grid::check_room(path, bytes)
}

/// The grid file a finished calibration produced on `device` with `config`: the lattice, the
/// device, the parameters used, what was measured at each vertex and, for a device whose profile
/// has an arm, the arm model and the model chosen by held-out score (format 2, `with_model`).
pub fn grid_file(result: &CalibrationResult, config: &Config, device: &DeviceSpec) -> GridFile {
    let c = &config.calibration;
    let i = &result.initial;
    let mm = |v: nalgebra::Vector3<f64>| (v * 1e3).into();
    let mut file = GridFile::from(MassGrid {
        g: c.g,
        gravity_direction: result.gravity_direction,
        origin: result.origin,
        spacing: c.spacing_mm * 1e-3,
        dims: result.dims,
        masses: result.vertices.iter().map(|v| v.mass).collect(),
    });
    file.device = Some(device_record(device));
    let created = humantime::format_rfc3339_seconds(SystemTime::now()).to_string();
    file.calibration = Some(CalibrationRecord {
        created: created.parse().ok(),
        hgcd_version: Some(env!("CARGO_PKG_VERSION").into()),
        spacing_mm: Some(c.spacing_mm),
        half_size: Some(c.half_size),
        // An explored grid's paper indices count from X_C, where exploration started.
        centre_mm: Some(
            result
                .workspace
                .as_ref()
                .map_or(c.centre_mm, |w| mm(w.centre)),
        ),
        k_init_n_per_mm: Some(c.k_init_n_per_mm),
        init_damping_n_s_per_m: Some(c.init_damping_n_s_per_m),
        n_init: Some(c.n_init),
        eps_init_mm: Some(c.eps_init_mm),
        n_m: Some(c.n_m),
        eps_m_mm: Some(c.eps_m_mm),
        rise_time_ms: Some(c.rise_time_ms),
        damping_ratio: Some(c.damping_ratio),
        move_time_ms: Some(c.move_time_ms),
        vertex_timeout_s: Some(c.vertex_timeout_s),
        max_iterations: Some(c.max_iterations),
        workspace_min_mm: Some(config.device.workspace_min_mm),
        workspace_max_mm: Some(config.device.workspace_max_mm),
        initial_mass_kg: Some(result.initial_mass),
        rest_point_mm: Some(mm(result.rest_point)),
        duration_s: Some(result.duration),
        left_out_vertices: Some(result.left_out.iter().map(|v| v.index).collect()),
        unreachable_vertices: Some(result.unreachable.iter().map(|v| v.index).collect()),
        workspace: Some(
            match result.workspace {
                Some(_) => "explore",
                None => "cube",
            }
            .into(),
        ),
        extrapolated_vertices: Some(result.extrapolated.iter().map(|v| v.index).collect()),
        load_n: Some(i.load.into()),
        friction_n: Some(i.friction.into()),
        sliding_friction_n: i.sliding_friction.map(Into::into),
        inertia_kg: Some(i.inertia.into()),
        noise_mm: Some(i.noise * 1e3),
        step_mm: Some(i.step * 1e3),
        stiffness_n_per_mm: Some((i.stiffness * 1e-3).into()),
    });
    file.vertices = VertexRecords {
        force_vectors: result.vertices.iter().map(|v| v.force.into()).collect(),
        iterations: result.vertices.iter().map(|v| v.iterations).collect(),
        final_error_mm: result
            .vertices
            .iter()
            .map(|v| v.final_error * 1e3)
            .collect(),
        friction_n: result.vertices.iter().map(|v| v.friction.into()).collect(),
    };
    with_model(&mut file, result, device, config);
    file
}

/// Fit the arm model to the grid's holds and choose the model by held-out score
/// ([`fit::choose`]), recording both in `file`; nothing for a device whose profile has no arm
/// (its file stays format 1, compensated as before).
fn with_model(
    file: &mut GridFile,
    result: &CalibrationResult,
    device: &DeviceSpec,
    config: &Config,
) {
    let profile = match Profile::for_device(device, config) {
        Ok(profile) => profile,
        Err(e) => {
            warn!("no arm model: {e}");
            return;
        }
    };
    let Some(arm) = profile.gravity_arm() else {
        return;
    };
    let grid = &file.grid;
    let measured = file.measured();
    let positions: Vec<_> = (0..grid.vertex_count())
        .map(|n| {
            let (i, j, k) = grid.coordinates(n);
            grid.vertex_position(i, j, k)
        })
        .collect();
    let holds = (0..grid.vertex_count())
        .map(|n| {
            let force = file.vertices.force_vectors.get(n)?;
            measured[n].then(|| Hold::new(positions[n], (*force).into()))
        })
        .collect();
    let held = result
        .vertices
        .iter()
        .zip(&measured)
        .map(|(v, &m)| (m && v.reached).then(|| Hold::new(v.measured_at, v.held_force)))
        .collect();
    let lattice = LatticeHolds {
        dims: grid.dims,
        positions,
        holds,
        measured: held,
        up: grid.gravity_direction,
        g: grid.g,
        linear_fill: file.explored(),
    };
    let choice = fit::choose(&lattice, Some(&arm), &profile.geometry_tolerances);
    let record = match &choice.arm {
        Some(Ok(fit)) => Some(ArmRecord {
            rank: fit.rank,
            unidentified: fit.unidentified.iter().map(|s| s.to_string()).collect(),
            condition: fit.condition,
            rms_residual_mn: fit.rms_residual * 1e3,
            normalised_residual: fit.normalised_residual,
            tilt_deg: fit.tilt.to_degrees(),
            profile_rms_residual_mn: choice
                .geometry
                .as_ref()
                .map(|g| g.profile_rms_residual * 1e3),
            geometry_change: choice.geometry.as_ref().map(|g| g.describe()),
            ..ArmRecord::new(&profile.name, &fit.gravity)
        }),
        _ => None,
    };
    // A fit the file format would refuse must not cost the calibration: the lattice stays. (A
    // fit that failed was never chosen.)
    let (record, mode, warning) = match record.map(|r| r.check().map(|()| r)) {
        Some(Err(problem)) => (
            None,
            CompensationMode::Vector,
            Some(format!("the arm model was not kept: {problem}")),
        ),
        record => (record.and_then(Result::ok), choice.mode, choice.warning()),
    };
    if let Some(w) = &warning {
        warn!("{w}");
    }
    file.arm = record;
    let s = &choice.scores;
    file.model = Some(ModelRecord {
        chosen: mode.to_string(),
        held_out_holds: choice.held_out,
        held_out_pct: HeldOutRecord {
            scalar: Some(s.scalar),
            vector: Some(s.vector),
            arm: s.arm,
            arm_residual: s.arm_residual,
        },
        warning,
    });
}
