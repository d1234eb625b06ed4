//! The apparent-mass grid and its `hgcd-grid/1` file (`docs/grid-format.md`). This module alone
//! knows the file's keys:
//! - `lattice`: [`MassGrid`], the vertices and the trilinear interpolation the servo path uses;
//! - `file`: [`GridFile`], the file format: the lattice plus typed provenance and per-vertex
//!   records, parsed with serde and checked against physical ranges;
//! - `store`: where grids live and how they are read and written: only regular files, bounded,
//!   never blocking; atomic replace with a backup that needs no data space; a room check;
//! - `effect`: the `hgcd-model/1` file, the effect `hgcd analyze` found beside a grid;
//! - `change`: a payload and a base tilt taken into a grid file (`hgcd check --apply`);
//! - `fill`: a lattice's unknown vertices filled from their neighbours;
//! - `identity`: which device a grid belongs to ([`DeviceIdentity`]): its model and serial
//!   number when the device names itself, else the spec it was opened with.

mod change;
mod effect;
mod file;
mod fill;
#[cfg(test)]
mod fuzz;
mod identity;
mod lattice;
mod store;

use std::path::PathBuf;

use thiserror::Error;

use lattice::{DIM_RANGE, MAX_VERTICES};

pub use change::{AppliedRecord, Change, ChangeError, PAYLOAD_FIT_SHARE};
pub use effect::{EffectRecord, ModelFile, ModelFileError, MODEL_FORMAT};
/// Grid files as a calibration writes them, for other modules' tests.
#[cfg(test)]
pub(crate) use file::tests as file_tests;
pub use file::{
    ArmRecord, CalibrationRecord, DeviceRecord, GridFile, HeldOutRecord, ModelRecord, UnitRecord,
    VertexRecords, GRID_FORMAT, GRID_FORMAT_2,
};
pub use fill::{extrapolate_from_neighbours, fill_from_neighbours, Field};
pub use identity::DeviceIdentity;
pub use lattice::{CellWeights, MassGrid, G_RANGE, MAX_MASS_KG, SPACING_RANGE};
pub use store::{check_room, grid_path, restore_backup};

/// Why a grid could not be loaded, built or saved.
#[derive(Debug, Error)]
pub enum GridError {
    /// Nothing exists at the path (not even a dangling symbolic link).
    #[error("no grid file at {path}")]
    Missing { path: PathBuf },
    #[error(
        "grid file {path} is {kind}, not a regular file (remove it, or put a grid file there)"
    )]
    NotRegular { path: PathBuf, kind: &'static str },
    #[error(
        "grid file {path} is a symbolic link to {target}, which does not exist (remove the link, \
         or put a grid file there)"
    )]
    DanglingLink { path: PathBuf, target: PathBuf },
    #[error("cannot read grid file {path}")]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("grid file {path} is over {max} bytes, the most a grid file may have")]
    TooLarge { path: PathBuf, max: u64 },
    #[error("grid file {path} is not valid TOML: {message}")]
    Syntax { path: PathBuf, message: String },
    #[error("grid file {path}: {problem}")]
    Invalid { path: PathBuf, problem: Problem },
    #[error("grid {path} was calibrated on another unit ({made_on}), not on this one ({unit})")]
    OtherUnit {
        path: PathBuf,
        made_on: Box<UnitRecord>,
        unit: Box<UnitRecord>,
    },
    #[error("grid {path} was made for device `{made_for}`, not `{device}`")]
    OtherDevice {
        path: PathBuf,
        made_for: String,
        device: String,
    },
    #[error("cannot write grid file {path}")]
    Write {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot create the state directory {dir} (use --state-dir or --output)")]
    CreateDir {
        dir: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error(
        "cannot write a {bytes}-byte grid file in {dir} (read-only, full, over quota or over the \
         file size limit; free some space, or use --state-dir or --output)"
    )]
    NoRoom {
        dir: PathBuf,
        bytes: u64,
        #[source]
        source: std::io::Error,
    },
}

/// What is wrong with the content of a grid file (`docs/grid-format.md` §3).
#[derive(Clone, Debug, PartialEq, Error)]
pub enum Problem {
    #[error(
        "`format` is {found}, expected \"{GRID_FORMAT}\" or \"{GRID_FORMAT_2}\" (not an hgcd grid, or \
         a newer version)"
    )]
    Format { found: String },
    /// A key is missing or a value has the wrong type; `at` is the line and its text, when the
    /// parser could point at one.
    #[error("{}{message}", at.as_ref().map(|(line, text)| format!("line {line} (`{text}`): ")).unwrap_or_default())]
    Schema {
        at: Option<(usize, String)>,
        message: String,
    },
    #[error("`{key}` is {value:?} {unit}, expected {min:?} to {max:?} {unit}")]
    OutOfRange {
        key: &'static str,
        value: f64,
        min: f64,
        max: f64,
        unit: &'static str,
    },
    #[error("`gravity_direction` must be a unit vector, its norm is {norm:?}")]
    NotUnit { norm: f64 },
    #[error(
        "`dims` entries must be integers from {} to {}, got {value}",
        DIM_RANGE.start(),
        DIM_RANGE.end()
    )]
    Dims { value: i64 },
    #[error("grid has {count} vertices, at most {MAX_VERTICES} are supported")]
    TooManyVertices { count: u64 },
    #[error("`masses` has {len} values but dims {dims:?} need {need}")]
    MassCount {
        len: usize,
        dims: [usize; 3],
        need: u64,
    },
    #[error(
        "mass at vertex {vertex} must be a finite number of kg, at most {MAX_MASS_KG:?} in magnitude, got {value:?}"
    )]
    Mass { vertex: usize, value: f64 },
    #[error("`[vertices] {key}` has {len} entries but the grid has {need} vertices")]
    PerVertexCount {
        key: &'static str,
        len: usize,
        need: usize,
    },
    #[error(
        "`[vertices] force_vectors` at vertex {vertex} is {value:?} N, expected finite components \
         and a norm up to {max:?} N"
    )]
    ForceVector {
        vertex: usize,
        value: [f64; 3],
        max: f64,
    },
    #[error("`[arm]`: {problem}")]
    Arm { problem: String },
    #[error(
        "`[model] chosen` is {chosen:?}: expected \"scalar\", \"vector\", \"arm\" or \
         \"arm-residual\", and an `[arm]` table for the arm models"
    )]
    Model { chosen: String },
    #[error(
        "`[vertices] final_error_mm` at vertex {vertex} must be a finite distance ≥ 0 mm, got \
         {value:?}"
    )]
    FinalError { vertex: usize, value: f64 },
    #[error(
        "`[vertices] friction_n` at vertex {vertex} is {value:?} N, expected finite components \
         from 0 to {max:?} N"
    )]
    Friction {
        vertex: usize,
        value: [f64; 3],
        max: f64,
    },
}
