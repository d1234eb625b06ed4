//! What a calibration leaves on disk: the grid file built from its result, and the check, made
//! before it starts, that the file will fit where it goes. Used by `hgcd calibrate` and by the
//! daemon's calibration on request alike.

use std::path::Path;
use std::time::SystemTime;

use super::{CalibrationResult, GridPlan};
use crate::config::{Config, DeviceSpec};
use crate::grid::{
    self, CalibrationRecord, DeviceRecord, GridError, GridFile, MassGrid, VertexRecords,
};

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
    let bytes = GridFile::size_bound(vertices, device.to_string().len());
    grid::check_room(path, bytes)
}

/// The grid file a finished calibration produced on `device` with `config`: the lattice, the
/// device, the parameters used and what was measured at each vertex.
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
        inertia_kg: Some(i.inertia.into()),
        noise_mm: Some(i.noise * 1e3),
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
    file
}
