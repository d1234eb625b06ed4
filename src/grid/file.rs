//! The `hgcd-grid/1` file format (`docs/grid-format.md`): the lattice's keys at the root, then the
//! typed records calibration adds (`[device]`, `[calibration]`, `[vertices]`), then any root keys
//! this version does not know, kept as read.

use std::path::Path;

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use super::lattice::{MassGrid, DIM_RANGE, G_RANGE, MAX_MASS_KG};
use super::{store, AppliedRecord, DeviceIdentity, GridError, Problem};
use crate::arm::{ArmTable, MAX_PARAMETERS};
use crate::config::CompensationMode;
use crate::protocol::{MODEL_LEN, SERIAL_LEN};

/// Format tag of version 1 grid files: a lattice and its records.
pub const GRID_FORMAT: &str = "hgcd-grid/1";
/// Format tag of version 2: version 1 with an arm model (`[arm]`, `[model]`); written only by a
/// calibration that fitted one, so every other file stays readable by older versions.
pub const GRID_FORMAT_2: &str = "hgcd-grid/2";

/// `[device]`: the device a grid was made for.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct DeviceRecord {
    /// Device id, as in the file name (`DeviceSpec::device_id`: `sim-point-mass`, `hid-1234-abcd-SN_7`).
    pub id: String,
    /// The spec the device was opened with (`hid:1234:abcd:SN 7`).
    pub spec: Option<String>,
    /// The unit the grid was calibrated on, as its device-info report named it
    /// (`docs/hid-protocol.md` §5a); none for a device that gave no report. `serial` is empty
    /// (or missing) for a device without one.
    pub model: Option<String>,
    pub serial: Option<String>,
}

impl DeviceRecord {
    /// The unit, when the device named itself.
    pub fn unit(&self) -> Option<UnitRecord> {
        self.model.as_ref().map(|model| UnitRecord {
            model: model.clone(),
            serial: self.serial.clone().unwrap_or_default(),
        })
    }
}

/// A unit: the model and serial of a device that named itself. `serial` is empty for a device
/// without one.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct UnitRecord {
    pub model: String,
    pub serial: String,
}

impl std::fmt::Display for UnitRecord {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if self.serial.is_empty() {
            write!(f, "{} without a serial number", self.model)
        } else {
            write!(f, "{} serial {}", self.model, self.serial)
        }
    }
}

/// `[calibration]`: how the grid was made. Parameters are in the units of their configuration keys
/// (`docs/calibration.md` §8.2). Every key may be missing: files of older versions have fewer.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CalibrationRecord {
    /// UTC time of the run.
    pub created: Option<toml::value::Datetime>,
    pub hgcd_version: Option<String>,
    pub spacing_mm: Option<f64>,
    pub half_size: Option<u32>,
    pub centre_mm: Option<[f64; 3]>,
    pub k_init_n_per_mm: Option<f64>,
    pub init_damping_n_s_per_m: Option<f64>,
    pub n_init: Option<usize>,
    pub eps_init_mm: Option<f64>,
    pub n_m: Option<usize>,
    pub eps_m_mm: Option<f64>,
    pub rise_time_ms: Option<f64>,
    pub damping_ratio: Option<f64>,
    pub move_time_ms: Option<f64>,
    pub vertex_timeout_s: Option<f64>,
    pub max_iterations: Option<u32>,
    /// The workspace box used (`device.workspace_*_mm`), mm.
    pub workspace_min_mm: Option<[f64; 3]>,
    pub workspace_max_mm: Option<[f64; 3]>,
    /// M̂₀ (Eq. 8), kg.
    pub initial_mass_kg: Option<f64>,
    /// X_C, the centre of the initialisation spring, mm.
    pub rest_point_mm: Option<[f64; 3]>,
    /// Device time of the whole run, s.
    pub duration_s: Option<f64>,
    /// Paper indices [n, m, p] of the vertices left out (outside the workspace).
    pub left_out_vertices: Option<Vec<[i32; 3]>>,
    /// Paper indices of the vertices the handle could not reach: their values are filled from
    /// their neighbours (`docs/grid-format.md` §4).
    pub unreachable_vertices: Option<Vec<[i32; 3]>>,
    /// "cube" (the paper's grid) or "explore" (the lattice over the explored workspace).
    pub workspace: Option<String>,
    /// Paper indices of an explored grid's vertices outside the explored workspace: never
    /// visited, their values extrapolated from the calibrated ones (`docs/grid-format.md` §4).
    pub extrapolated_vertices: Option<Vec<[i32; 3]>>,
    /// What the initialisation measured at X_C: the load (holding force), N; the friction (half
    /// the stick band) along x, y, z, N; the moving mass along x, y, z, kg; the position noise
    /// (standard deviation), mm; the encoder's step (or a few standard deviations of noise
    /// without one), mm; and the hold stiffness built from them, N/mm.
    pub load_n: Option<[f64; 3]>,
    pub friction_n: Option<[f64; 3]>,
    /// The sliding friction along x, y, z that the survey strokes at X_C measured, N (the
    /// bands' edges, read at a slip, usually put `friction_n` 5–30 % above it).
    pub sliding_friction_n: Option<[f64; 3]>,
    pub inertia_kg: Option<[f64; 3]>,
    pub noise_mm: Option<f64>,
    pub step_mm: Option<f64>,
    pub stiffness_n_per_mm: Option<[f64; 3]>,
}

/// `[vertices]`: what calibration measured at each vertex, in grid order. Each list is either
/// empty (absent from the file) or has one entry per vertex.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct VertexRecords {
    /// Holding force at the vertex's last steady state, N (what the vector mode interpolates).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub force_vectors: Vec<[f64; 3]>,
    /// Mass updates made.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub iterations: Vec<u32>,
    /// Distance from the vertex at the last steady state, mm.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub final_error_mm: Vec<f64>,
    /// Half the stick band along x, y and z: the friction at the vertex, N.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub friction_n: Vec<[f64; 3]>,
}

impl VertexRecords {
    /// True when no list has entries (the file then has no `[vertices]` table).
    pub fn is_empty(&self) -> bool {
        self.force_vectors.is_empty()
            && self.iterations.is_empty()
            && self.final_error_mm.is_empty()
            && self.friction_n.is_empty()
    }

    fn check(&self, vertices: usize) -> Result<(), Problem> {
        let lengths = [
            ("force_vectors", self.force_vectors.len()),
            ("iterations", self.iterations.len()),
            ("final_error_mm", self.final_error_mm.len()),
            ("friction_n", self.friction_n.len()),
        ];
        for (key, len) in lengths {
            if len != 0 && len != vertices {
                return Err(Problem::PerVertexCount {
                    key,
                    len,
                    need: vertices,
                });
            }
        }
        // The largest weight the mass and g ranges allow.
        let max = MAX_MASS_KG * G_RANGE.end();
        for (vertex, &value) in self.force_vectors.iter().enumerate() {
            if !(value.iter().all(|c| c.is_finite()) && Vector3::from(value).norm() <= max) {
                return Err(Problem::ForceVector { vertex, value, max });
            }
        }
        for (vertex, &value) in self.final_error_mm.iter().enumerate() {
            if !(value.is_finite() && value >= 0.0) {
                return Err(Problem::FinalError { vertex, value });
            }
        }
        for (vertex, &value) in self.friction_n.iter().enumerate() {
            if !value
                .iter()
                .all(|c| c.is_finite() && (0.0..=max).contains(c))
            {
                return Err(Problem::Friction { vertex, value, max });
            }
        }
        Ok(())
    }
}

/// `[arm]`: the arm model fitted to the holds (format 2): the profile's arm as it was used, its
/// base parameters and the gravity it was fitted under, and what the fit says of itself.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ArmRecord {
    /// The device profile the arm came from.
    pub profile: String,
    /// First moments, kg m (a delta's platform: a mass, kg), in the arm's order
    /// (`docs/grid-format.md` §4).
    pub parameters: Vec<f64>,
    /// Unit v_G of the fit (against gravity), and g, m/s².
    pub gravity_direction: [f64; 3],
    pub g: f64,
    /// Combinations of the parameters the holds identified, and the parameters dominating those
    /// they left unconstrained.
    pub rank: usize,
    pub unidentified: Vec<String>,
    /// Conditioning of the identified combinations.
    pub condition: f64,
    /// RMS of |F − F̂| over the holds, mN, and of its components over each hold's noise.
    pub rms_residual_mn: f64,
    pub normalised_residual: f64,
    /// Angle between the fitted v_G and the arm's own up, degrees.
    pub tilt_deg: f64,
    /// Where the calibration estimated the unit's own geometry (`fit::geometry`): the RMS
    /// residual the profile's geometry left, mN, and what changed, in words.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub profile_rms_residual_mn: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub geometry_change: Option<String>,
    /// The arm's geometry and frame (`[arm.geometry]`, as in the profile; the unit's own where
    /// the calibration estimated it).
    pub geometry: ArmTable,
}

impl ArmRecord {
    /// The record of the arm model `gravity`, from the profile `profile`, with the statistics of
    /// an exact fit (every parameter identified, no residual); a fit sets its own.
    pub fn new(profile: &str, gravity: &crate::arm::ArmGravity) -> Self {
        let count = gravity.arm.parameter_count();
        Self {
            profile: profile.to_string(),
            parameters: gravity.parameters[..count].to_vec(),
            gravity_direction: gravity.up.into(),
            g: gravity.g,
            rank: count,
            unidentified: Vec::new(),
            condition: 1.0,
            rms_residual_mn: 0.0,
            normalised_residual: 0.0,
            tilt_deg: gravity.up.angle(&gravity.arm.up()).to_degrees(),
            profile_rms_residual_mn: None,
            geometry_change: None,
            geometry: ArmTable::of(&gravity.arm),
        }
    }

    /// The arm model is whole: a geometry that loads, a finite parameter for each of its
    /// parameters, a unit gravity direction, g in range.
    ///
    /// Errors: [`Problem::Arm`] naming the key, [`Problem::OutOfRange`] for `g`.
    pub fn check(&self) -> Result<(), Problem> {
        let arm = self
            .geometry
            .arm()
            .map_err(|problem| Problem::Arm { problem })?;
        let count = arm.parameter_count();
        if self.parameters.len() != count || count > MAX_PARAMETERS {
            return Err(Problem::Arm {
                problem: format!(
                    "`parameters` has {} values, a {} arm has {count}",
                    self.parameters.len(),
                    arm.kind()
                ),
            });
        }
        if let Some(&value) = self
            .parameters
            .iter()
            .find(|p| !(p.is_finite() && p.abs() <= MAX_MOMENT))
        {
            return Err(Problem::Arm {
                problem: format!("a parameter is {value:?}, expected a finite first moment within ±{MAX_MOMENT} kg m"),
            });
        }
        let norm = Vector3::from(self.gravity_direction).norm();
        if (norm - 1.0).abs() >= 1e-6 || norm.is_nan() {
            return Err(Problem::Arm {
                problem: format!("`gravity_direction` must be a unit vector, its norm is {norm:?}"),
            });
        }
        if !G_RANGE.contains(&self.g) {
            return Err(Problem::OutOfRange {
                key: "arm.g",
                value: self.g,
                min: *G_RANGE.start(),
                max: *G_RANGE.end(),
                unit: "m/s²",
            });
        }
        Ok(())
    }

    /// The arm model this record describes (checked by [`GridFile::check`] when loaded).
    pub fn gravity(&self) -> Result<crate::arm::ArmGravity, Problem> {
        self.check()?;
        let mut parameters = [0.0; MAX_PARAMETERS];
        parameters[..self.parameters.len()].copy_from_slice(&self.parameters);
        Ok(crate::arm::ArmGravity {
            arm: self
                .geometry
                .arm()
                .map_err(|problem| Problem::Arm { problem })?,
            parameters,
            up: Vector3::from(self.gravity_direction),
            g: self.g,
        })
    }
}

/// The largest first moment (or platform mass) an arm record may hold, kg m (kg).
pub const MAX_MOMENT: f64 = 100.0;

/// `[model]`: which model compensates (format 2), and the held-out scores that chose it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ModelRecord {
    /// "scalar", "vector", "arm" or "arm-residual".
    pub chosen: String,
    /// Holds kept out of the fits.
    pub held_out_holds: usize,
    /// 100 √(Σ|F − F̂|² / Σ|F|²) over the held-out holds, %, per candidate (a candidate missing
    /// could not be fitted).
    pub held_out_pct: HeldOutRecord,
    /// Why the arm model was not chosen or is off, if it was not or is.
    pub warning: Option<String>,
}

/// `[model.held_out_pct]`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct HeldOutRecord {
    pub scalar: Option<f64>,
    pub vector: Option<f64>,
    pub arm: Option<f64>,
    pub arm_residual: Option<f64>,
}

impl HeldOutRecord {
    /// The score of `mode`, if it was scored.
    pub fn of(&self, mode: CompensationMode) -> Option<f64> {
        match mode {
            CompensationMode::Scalar => self.scalar,
            CompensationMode::Vector => self.vector,
            CompensationMode::Arm => self.arm,
            CompensationMode::ArmResidual => self.arm_residual,
        }
    }
}

/// An `hgcd-grid/1` or `/2` file: the lattice and what was recorded with it.
#[derive(Clone, Debug, PartialEq)]
pub struct GridFile {
    pub grid: MassGrid,
    pub device: Option<DeviceRecord>,
    pub calibration: Option<CalibrationRecord>,
    pub vertices: VertexRecords,
    /// The arm model and the choice of model (format 2).
    pub arm: Option<ArmRecord>,
    pub model: Option<ModelRecord>,
    /// `[[applied]]`: the changes `hgcd check --apply` took into the model since the
    /// calibration, oldest first.
    pub applied: Vec<AppliedRecord>,
    /// Root keys this version does not know: kept as read and written back (format §4).
    extra: toml::Table,
}

impl From<MassGrid> for GridFile {
    /// A file holding the lattice alone.
    fn from(grid: MassGrid) -> Self {
        Self {
            grid,
            device: None,
            calibration: None,
            vertices: VertexRecords::default(),
            arm: None,
            model: None,
            applied: Vec::new(),
            extra: toml::Table::new(),
        }
    }
}

/// The file as serde reads it.
#[derive(Deserialize)]
struct Raw {
    format: String,
    g: f64,
    gravity_direction: [f64; 3],
    origin: [f64; 3],
    spacing: f64,
    dims: [i64; 3],
    masses: Vec<f64>,
    device: Option<DeviceRecord>,
    calibration: Option<CalibrationRecord>,
    #[serde(default)]
    vertices: VertexRecords,
    arm: Option<ArmRecord>,
    model: Option<ModelRecord>,
    #[serde(default)]
    applied: Vec<AppliedRecord>,
    #[serde(flatten)]
    extra: toml::Table,
}

/// Everything after the lattice, as serde writes it.
#[derive(Serialize)]
struct Records<'a> {
    device: &'a Option<DeviceRecord>,
    calibration: &'a Option<CalibrationRecord>,
    #[serde(skip_serializing_if = "VertexRecords::is_empty")]
    vertices: &'a VertexRecords,
    model: &'a Option<ModelRecord>,
    arm: &'a Option<ArmRecord>,
    #[serde(skip_serializing_if = "<[_]>::is_empty")]
    applied: &'a [AppliedRecord],
    #[serde(flatten)]
    extra: &'a toml::Table,
}

impl GridFile {
    /// The unit the grid was calibrated on (`[device] model` and `serial`), if it named itself.
    pub fn unit(&self) -> Option<UnitRecord> {
        self.device.as_ref().and_then(DeviceRecord::unit)
    }

    /// Check every value against the format's rules (`docs/grid-format.md` §3).
    ///
    /// Errors: the first [`Problem`] found, in the order of the format's table.
    pub fn check(&self) -> Result<(), Problem> {
        self.grid.check()?;
        self.vertices.check(self.grid.vertex_count())?;
        if let Some(arm) = &self.arm {
            arm.check()?;
        }
        if let Some(model) = &self.model {
            let chosen = model.chosen.parse::<CompensationMode>();
            let needs_arm = matches!(
                chosen,
                Ok(CompensationMode::Arm | CompensationMode::ArmResidual)
            );
            if chosen.is_err() || (needs_arm && self.arm.is_none()) {
                return Err(Problem::Model {
                    chosen: model.chosen.clone(),
                });
            }
        }
        Ok(())
    }

    /// Whether this is an explored grid (`[calibration] workspace = "explore"`), whose vertices
    /// not measured are extrapolated along straight lines rather than filled with their
    /// neighbours' mean.
    pub fn explored(&self) -> bool {
        self.calibration
            .as_ref()
            .and_then(|c| c.workspace.as_deref())
            == Some("explore")
    }

    /// Fill the vertices of `values` (grid order) that `measured` does not mark from those it
    /// does, as the calibration filled this grid's: along straight lines on an explored grid,
    /// with the neighbours' mean otherwise. Nothing to fill from, nothing is filled.
    pub fn fill_unmeasured<T: super::Field>(&self, values: &mut [T], measured: &[bool]) {
        if !measured.contains(&true) {
            return;
        }
        if self.explored() {
            super::extrapolate_from_neighbours(self.grid.dims, values, measured);
        } else {
            super::fill_from_neighbours(self.grid.dims, values, measured);
        }
    }

    /// The format tag this file is written with: 2 with an arm model, else 1.
    pub fn format(&self) -> &'static str {
        if self.arm.is_some() || self.model.is_some() {
            GRID_FORMAT_2
        } else {
            GRID_FORMAT
        }
    }

    /// Per vertex, grid order: whether its values were measured (not listed by `[calibration]`
    /// as unreachable or extrapolated).
    pub fn measured(&self) -> Vec<bool> {
        let grid = &self.grid;
        let mut measured = vec![true; grid.masses.len()];
        if let Some(c) = &self.calibration {
            let centre = Vector3::from(c.centre_mm.unwrap_or_default()) * 1e-3;
            let listed = c
                .unreachable_vertices
                .iter()
                .chain(&c.extrapolated_vertices);
            for k in listed.flatten() {
                let x = centre + Vector3::new(k[0] as f64, k[1] as f64, k[2] as f64) * grid.spacing;
                let i = ((x - grid.origin) / grid.spacing).map(|u| u.round());
                if (0..3).all(|a| i[a] >= 0.0 && (i[a] as usize) < grid.dims[a]) {
                    measured[grid.index(i[0] as usize, i[1] as usize, i[2] as usize)] = false;
                }
            }
        }
        measured
    }

    /// Parse and check a grid from TOML text; `path` names the source in messages. Errors:
    /// [`GridError::Syntax`], [`GridError::Invalid`].
    pub fn from_toml_str(text: &str, path: &Path) -> Result<Self, GridError> {
        let invalid = |problem| GridError::Invalid {
            path: path.to_path_buf(),
            problem,
        };
        let raw: Raw = toml::from_str(text).map_err(|e| diagnose(text, &e, path))?;
        if raw.format != GRID_FORMAT && raw.format != GRID_FORMAT_2 {
            return Err(invalid(Problem::Format {
                found: format!("{:?}", raw.format),
            }));
        }
        let mut dims = [0usize; 3];
        for (d, &n) in dims.iter_mut().zip(&raw.dims) {
            if !DIM_RANGE.contains(&n) {
                return Err(invalid(Problem::Dims { value: n }));
            }
            *d = n as usize;
        }
        let mut file = Self {
            grid: MassGrid {
                g: raw.g,
                gravity_direction: Vector3::from(raw.gravity_direction),
                origin: Vector3::from(raw.origin),
                spacing: raw.spacing,
                dims,
                masses: raw.masses,
            },
            device: raw.device,
            calibration: raw.calibration,
            vertices: raw.vertices,
            arm: raw.arm,
            model: raw.model,
            applied: raw.applied,
            extra: raw.extra,
        };
        file.check().map_err(invalid)?;
        file.grid.gravity_direction.normalize_mut();
        Ok(file)
    }

    /// Load and check the grid file at `path` (a regular file of at most 64 MiB). Errors:
    /// [`GridError::Missing`] when nothing exists at `path`, and every other variant a read or a
    /// parse gives.
    pub fn load(path: &Path) -> Result<Self, GridError> {
        Self::from_toml_str(&store::read_regular(path)?, path)
    }

    /// [`load`](Self::load), and refuse a grid calibrated on another unit than `device`'s (both
    /// name a serial number, and they or the models differ: [`GridError::OtherUnit`]), or one
    /// whose `[device] id` names another device ([`GridError::OtherDevice`]). A grid that names
    /// no device is returned; its `device` is `None`.
    pub fn load_for(path: &Path, device: &DeviceIdentity) -> Result<Self, GridError> {
        let file = Self::load(path)?;
        if let (Some(made_on), Some(unit)) = (file.unit(), device.unit()) {
            let serials = !made_on.serial.is_empty() && !unit.serial.is_empty();
            if serials && made_on != unit {
                return Err(GridError::OtherUnit {
                    path: path.to_path_buf(),
                    made_on: Box::new(made_on),
                    unit: Box::new(unit),
                });
            }
        }
        let id = device.grid_id();
        match &file.device {
            Some(d) if d.id != id => Err(GridError::OtherDevice {
                path: path.to_path_buf(),
                made_for: d.id.clone(),
                device: id,
            }),
            _ => Ok(file),
        }
    }

    /// Render as `hgcd-grid/1` TOML: the lattice's keys in the order of format §2 (`masses` one
    /// row of nx values per line), then the records, then the unknown keys kept.
    pub fn to_toml_string(&self) -> String {
        let g = &self.grid;
        let vec3 = |v: &Vector3<f64>| format!("[{:?}, {:?}, {:?}]", v.x, v.y, v.z);
        let mut out = format!(
            "format = \"{}\"\ng = {:?}\ngravity_direction = {}\norigin = {}\n\
             spacing = {:?}\ndims = [{}, {}, {}]\nmasses = [\n",
            self.format(),
            g.g,
            vec3(&g.gravity_direction),
            vec3(&g.origin),
            g.spacing,
            g.dims[0],
            g.dims[1],
            g.dims[2]
        );
        for chunk in g.masses.chunks(g.dims[0].max(1)) {
            let row: Vec<String> = chunk.iter().map(|m| format!("{m:?}")).collect();
            out.push_str(&format!("  {},\n", row.join(", ")));
        }
        out.push_str("]\n");
        let records = Records {
            device: &self.device,
            calibration: &self.calibration,
            vertices: &self.vertices,
            model: &self.model,
            arm: &self.arm,
            applied: &self.applied,
            extra: &self.extra,
        };
        // Plain structs of numbers, strings, arrays and tables always serialise; the fallback
        // only keeps the type honest.
        let tail = toml::to_string(&records)
            .unwrap_or_else(|e| format!("# records could not be written: {e}\n"));
        if !tail.is_empty() {
            out.push('\n');
            out.push_str(&tail);
        }
        out
    }

    /// Check, then write atomically to `path`, keeping the file there as `<name>.bak`
    /// (`docs/grid-format.md` §7). A grid that would not load is not written
    /// ([`GridError::Invalid`]); on a write error ([`GridError::Write`]) `path` and its backup
    /// are unchanged and no partial file is left.
    pub fn save_atomic(&self, path: &Path) -> Result<(), GridError> {
        self.check().map_err(|problem| GridError::Invalid {
            path: path.to_path_buf(),
            problem,
        })?;
        store::replace_atomically(path, self.to_toml_string().as_bytes())
    }

    /// An upper bound on the size, in bytes, of the file a calibration of `vertices` vertices
    /// (those left out included) writes for a device spec of `spec_len` bytes.
    pub fn size_bound(vertices: usize, spec_len: usize) -> u64 {
        // Lattice keys and the calibration record: under 3 KiB. Per vertex: a mass, a force
        // vector, an iteration count, an error and a friction vector, each number at most 24
        // characters, with separators, about 260 bytes; a left-out or unreachable vertex's
        // indices take less. The unit's model and serial, every byte escaped at worst, and an id
        // made of them.
        let unit = 4 * (MODEL_LEN + SERIAL_LEN) as u64 + 64;
        4096 + 2 * spec_len as u64 + unit + 384 * vertices as u64
    }
}

/// Why `text` did not deserialise: a TOML syntax error, a wrong `format` (reported first, since a
/// newer version's keys need not match), or a missing key or a wrongly typed value.
fn diagnose(text: &str, error: &toml::de::Error, path: &Path) -> GridError {
    let message = in_our_words(error.message());
    match text.parse::<toml::Table>() {
        Err(syntax) => GridError::Syntax {
            path: path.to_path_buf(),
            message: match syntax.span() {
                Some(span) => format!(
                    "line {}: {}",
                    line_of(text, span.start).0,
                    one_line(syntax.message())
                ),
                None => one_line(syntax.message()),
            },
        },
        Ok(table) => {
            let problem = match table.get("format") {
                Some(found)
                    if found.as_str() != Some(GRID_FORMAT)
                        && found.as_str() != Some(GRID_FORMAT_2) =>
                {
                    Problem::Format {
                        found: clip(&found.to_string(), 60),
                    }
                }
                _ => Problem::Schema {
                    at: error.span().and_then(|span| {
                        let (line, line_text) = line_of(text, span.start);
                        // A span over several lines is a table: name it by its header. The root
                        // table has no header worth showing.
                        let multi_line = line_text.len() < span.end - span.start;
                        (!multi_line || line_text.starts_with('['))
                            .then(|| (line, clip(line_text.trim(), 60)))
                    }),
                    message,
                },
            };
            GridError::Invalid {
                path: path.to_path_buf(),
                problem,
            }
        }
    }
}

/// The 1-based line number of byte `at` in `text`, and that line.
fn line_of(text: &str, at: usize) -> (usize, &str) {
    let at = at.min(text.len());
    let start = text[..at].rfind('\n').map_or(0, |n| n + 1);
    let end = text[at..].find('\n').map_or(text.len(), |n| at + n);
    (text[..at].matches('\n').count() + 1, &text[start..end])
}

fn one_line(message: &str) -> String {
    clip(&message.trim().replace('\n', "; "), 200)
}

/// A deserialisation message in the format's words: keys, numbers and integers.
fn in_our_words(message: &str) -> String {
    one_line(message)
        .replace("missing field", "missing required key")
        .replace("expected f64", "expected a number")
        .replace("expected i64", "expected an integer")
        .replace("expected i32", "expected an integer")
        .replace("expected u32", "expected an integer ≥ 0")
        .replace("expected usize", "expected an integer ≥ 0")
}

/// `s`, cut to at most `max` characters.
fn clip(s: &str, max: usize) -> String {
    match s.char_indices().nth(max) {
        Some((cut, _)) => format!("{}…", &s[..cut]),
        None => s.to_string(),
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::grid::lattice::tests::sample;

    /// A grid file with every record filled in, as a calibration writes it.
    pub(crate) fn calibrated() -> GridFile {
        let mut file = GridFile::from(sample());
        file.device = Some(DeviceRecord {
            id: "sim-point-mass".into(),
            spec: Some("sim:point-mass".into()),
            model: Some("sim-point-mass".into()),
            serial: Some("SIM-7".into()),
        });
        file.calibration = Some(CalibrationRecord {
            created: Some("2026-11-21T23:29:02Z".parse().unwrap()),
            hgcd_version: Some("0.1.0".into()),
            spacing_mm: Some(40.0),
            half_size: Some(1),
            rest_point_mm: Some([0.0, -0.005, 0.0]),
            duration_s: Some(26.195),
            left_out_vertices: Some(vec![[-2, -2, -2]]),
            ..CalibrationRecord::default()
        });
        let n = file.grid.vertex_count();
        file.vertices = VertexRecords {
            force_vectors: (0..n).map(|i| [1e-6 * i as f64, 0.0, 1.2]).collect(),
            iterations: vec![2; n],
            final_error_mm: vec![0.0071278015934572074; n],
            friction_n: vec![[0.05, 0.048, 0.0]; n],
        };
        file
    }

    fn parse(text: &str) -> Result<GridFile, GridError> {
        GridFile::from_toml_str(text, Path::new("t.toml"))
    }

    fn problem(text: &str) -> Problem {
        match parse(text) {
            Err(GridError::Invalid { problem, .. }) => problem,
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn round_trip_keeps_records_and_unknown_keys() {
        let mut file = calibrated();
        file.extra
            .insert("note".into(), toml::Value::String("hand-made".into()));
        let mut later = toml::Table::new();
        later.insert(
            "when".into(),
            toml::Value::Datetime("1979-05-27".parse().unwrap()),
        );
        file.extra
            .insert("future".into(), toml::Value::Table(later));
        let text = file.to_toml_string();
        assert_eq!(parse(&text).unwrap(), file);
        // The lattice comes first, one row of masses per line.
        assert!(
            text.starts_with("format = \"hgcd-grid/1\"\ng = 9.81\n"),
            "{text}"
        );
        assert!(
            text.contains("masses = [\n  0.05, 0.060000000000000005, 0.07,\n"),
            "{text}"
        );
        // A bare lattice has nothing after `masses`.
        assert!(GridFile::from(sample()).to_toml_string().ends_with("]\n"));
    }

    #[test]
    fn files_written_by_earlier_versions_load() {
        // The first release wrote `rest_point_m` and fewer parameters; its tables still read.
        let text = format!(
            "{}\n[calibration]\ncreated = 2025-01-02T03:04:05Z\nhgcd_version = \"0.0.1\"\n\
             spacing_mm = 40.0\nhalf_size = 1\nrest_point_m = [0.0, 0.0, 0.0]\nduration_s = 30.5\n\n\
             [device]\nid = \"sim-point-mass\"\nspec = \"sim:point-mass\"\n\n[vertices]\n\
             final_error_mm = [{errors}]\nforce_vectors = [{forces}]\niterations = [{iterations}]\n",
            GridFile::from(sample()).to_toml_string(),
            errors = vec!["0.01"; 27].join(", "),
            forces = vec!["[0.0, 0.0, 1.0]"; 27].join(", "),
            iterations = vec!["3"; 27].join(", "),
        );
        let file = parse(&text).unwrap();
        let c = file.calibration.unwrap();
        assert_eq!(c.duration_s, Some(30.5));
        assert_eq!(c.rest_point_mm, None);
        assert_eq!(file.device.unwrap().id, "sim-point-mass");
        assert_eq!(file.vertices.iterations, vec![3; 27]);
    }

    #[test]
    fn the_example_of_the_format_document_loads() {
        let doc = include_str!("../../docs/grid-format.md");
        let example = doc
            .split("```toml\n")
            .nth(1)
            .and_then(|rest| rest.split("```").next())
            .unwrap();
        let file = parse(example).unwrap();
        // §8: M = 0.1294375 kg at (0.010, −0.030, 0.020) m.
        let m = file.grid.mass_at(&Vector3::new(0.010, -0.030, 0.020));
        assert!((m - 0.1294375).abs() < 1e-12, "{m}");
    }

    #[test]
    fn bad_files_are_refused_with_what_is_wrong() {
        let good = calibrated().to_toml_string();
        assert!(matches!(
            problem(&good.replace("hgcd-grid/1", "hgcd-grid/9")),
            Problem::Format { found } if found == "\"hgcd-grid/9\""
        ));
        // A newer version's keys need not match ours: the format is what is reported.
        assert!(matches!(
            problem("format = \"hgcd-grid/3\"\nlattice = 1\n"),
            Problem::Format { .. }
        ));
        assert!(matches!(
            problem(&good.replace("dims = [3, 3, 3]", "dims = [3, 3, 4]")),
            Problem::MassCount {
                len: 27,
                need: 36,
                ..
            }
        ));
        assert!(matches!(
            problem(&good.replace("dims = [3, 3, 3]", "dims = [3, 0, 3]")),
            Problem::Dims { value: 0 }
        ));
        assert!(matches!(
            problem(&good.replace("[0.0, 0.0, 1.0]", "[0.0, 0.0, 2.0]")),
            Problem::NotUnit { .. }
        ));
        for bad in ["-1e9", "nan", "-inf", "1e9"] {
            assert!(
                matches!(
                    problem(&good.replacen("0.05, ", &format!("{bad}, "), 1)),
                    Problem::Mass { vertex: 0, .. }
                ),
                "{bad}"
            );
        }
        // Negative and zero masses load (issue 17: over-balanced arms); only the magnitude is
        // bounded.
        let signed = good.replacen("0.05, 0.060000000000000005", "-0.05, 0.0", 1);
        assert_eq!(parse(&signed).unwrap().grid.masses[..2], [-0.05, 0.0]);
        // Item 7 of issue 7: a grid with g = 1e308 loaded.
        assert!(matches!(
            problem(&good.replace("g = 9.81", "g = 1e308")),
            Problem::OutOfRange { key: "g", .. }
        ));
        assert!(matches!(
            problem(&good.replace("spacing = 0.04", "spacing = 40.0")),
            Problem::OutOfRange { key: "spacing", .. }
        ));
        match problem(&good.replace("spacing = 0.04\n", "")) {
            Problem::Schema { message, .. } => {
                assert_eq!(message, "missing required key `spacing`")
            }
            other => panic!("{other:?}"),
        }
        match problem(&good.replace("g = 9.81", "g = \"9.81\"")) {
            Problem::Schema {
                at: Some((2, line)),
                message,
            } => {
                assert_eq!(line, "g = \"9.81\"");
                assert_eq!(message, "invalid type: string \"9.81\", expected a number");
            }
            other => panic!("{other:?}"),
        }
        match problem(&good.replace("id = \"sim-point-mass\"", "name = \"x\"")) {
            Problem::Schema {
                at: Some((_, line)),
                message,
            } => {
                assert_eq!(line, "[device]");
                assert!(message.contains("`id`"), "{message}");
            }
            other => panic!("{other:?}"),
        }
        assert!(matches!(
            problem(&good.replace("iterations = [2, 2, ", "iterations = [2, ")),
            Problem::PerVertexCount {
                key: "iterations",
                len: 26,
                need: 27
            }
        ));
        for bad in ["nan]", "1e300]"] {
            assert!(matches!(
                problem(&good.replacen("1.2]", bad, 1)),
                Problem::ForceVector { vertex: 0, .. }
            ));
        }
        assert!(matches!(
            parse("format = "),
            Err(GridError::Syntax { message, .. }) if message.starts_with("line 1: ")
        ));
    }

    #[test]
    fn a_grid_for_another_device_is_refused_by_load_for() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("dev.toml");
        calibrated().save_atomic(&path).unwrap();
        let spec = |s: &str| DeviceIdentity::of_spec(s.parse().unwrap());
        assert!(GridFile::load_for(&path, &spec("sim:point-mass")).is_ok());
        match GridFile::load_for(&path, &spec("hid:1234:5678")) {
            Err(GridError::OtherDevice {
                made_for, device, ..
            }) => assert_eq!(
                (made_for.as_str(), device.as_str()),
                ("sim-point-mass", "hid-1234-5678")
            ),
            other => panic!("{other:?}"),
        }
        // A grid that names no device is anybody's.
        GridFile::from(sample()).save_atomic(&path).unwrap();
        assert_eq!(
            GridFile::load_for(&path, &spec("hid:1234:5678"))
                .unwrap()
                .device,
            None
        );
    }

    #[test]
    fn a_grid_calibrated_on_another_unit_is_refused_in_one_line() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("dev.toml");
        let unit = |serial: &str| DeviceIdentity {
            spec: "socket:/run/dev.sock".parse().unwrap(),
            info: Some(crate::protocol::DeviceInfo {
                model: "PHANToM-like 3".into(),
                serial: serial.into(),
                workspace_centre: Vector3::zeros(),
                workspace_half_extents: Vector3::repeat(0.1),
                max_force: 3.0,
                rate_hz: 1000.0,
                lockstep: false,
            }),
        };
        let mut file = calibrated();
        unit("A-1").stamp(&mut file);
        file.save_atomic(&path).unwrap();
        let back = GridFile::load_for(&path, &unit("A-1")).unwrap();
        assert_eq!(back.unit(), unit("A-1").unit());
        assert_eq!(back.device.unwrap().id, "PHANToM-like_3-A-1");
        let err = GridFile::load_for(&path, &unit("B-2")).unwrap_err();
        assert!(matches!(err, GridError::OtherUnit { .. }), "{err}");
        let line = err.to_string();
        assert!(!line.contains('\n'));
        assert!(
            line.contains("PHANToM-like 3 serial A-1")
                && line.contains("PHANToM-like 3 serial B-2"),
            "{line}"
        );
        // A device that does not name itself is judged by its id alone.
        assert!(matches!(
            GridFile::load_for(
                &path,
                &DeviceIdentity::of_spec("socket:/run/dev.sock".parse().unwrap())
            ),
            Err(GridError::OtherDevice { .. })
        ));
    }

    #[test]
    fn a_grid_that_would_not_load_is_not_written() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("dev.toml");
        let mut file = calibrated();
        file.grid.masses[3] = f64::NAN;
        assert!(matches!(
            file.save_atomic(&path),
            Err(GridError::Invalid {
                problem: Problem::Mass { vertex: 3, .. },
                ..
            })
        ));
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    }

    #[test]
    fn the_size_bound_holds_for_the_longest_numbers() {
        let longest = -1.2345678901234567e-300;
        for dims in [[1, 1, 1], [3, 3, 3], [1, 1, 40], [40, 1, 1], [7, 5, 3]] {
            let n: usize = dims.iter().product();
            let mut grid = MassGrid::uniform(
                longest,
                longest,
                Vector3::z(),
                Vector3::zeros(),
                longest,
                dims,
            );
            grid.origin = Vector3::repeat(longest);
            let spec = format!("socket:/{}", "d".repeat(200));
            let mut file = GridFile::from(grid);
            file.device = Some(DeviceRecord {
                id: spec.clone(),
                spec: Some(spec.clone()),
                model: Some("\"".repeat(MODEL_LEN)),
                serial: Some("\\".repeat(SERIAL_LEN)),
            });
            file.calibration = Some(CalibrationRecord {
                created: Some("2026-11-21T23:29:02.123456789Z".parse().unwrap()),
                hgcd_version: Some("100.100.100-alpha.1".into()),
                spacing_mm: Some(longest),
                half_size: Some(u32::MAX),
                centre_mm: Some([longest; 3]),
                k_init_n_per_mm: Some(longest),
                init_damping_n_s_per_m: Some(longest),
                n_init: Some(usize::MAX),
                eps_init_mm: Some(longest),
                n_m: Some(usize::MAX),
                eps_m_mm: Some(longest),
                rise_time_ms: Some(longest),
                damping_ratio: Some(longest),
                move_time_ms: Some(longest),
                vertex_timeout_s: Some(longest),
                max_iterations: Some(u32::MAX),
                workspace_min_mm: Some([longest; 3]),
                workspace_max_mm: Some([longest; 3]),
                initial_mass_kg: Some(longest),
                rest_point_mm: Some([longest; 3]),
                duration_s: Some(longest),
                left_out_vertices: Some(vec![[i32::MIN; 3]; n]),
                unreachable_vertices: Some(vec![[i32::MIN; 3]; n]),
                workspace: Some("explore".into()),
                extrapolated_vertices: Some(vec![[i32::MIN; 3]; n]),
                load_n: Some([longest; 3]),
                friction_n: Some([longest; 3]),
                sliding_friction_n: Some([longest; 3]),
                inertia_kg: Some([longest; 3]),
                noise_mm: Some(longest),
                step_mm: Some(longest),
                stiffness_n_per_mm: Some([longest; 3]),
            });
            file.vertices = VertexRecords {
                force_vectors: vec![[longest; 3]; n],
                iterations: vec![u32::MAX; n],
                final_error_mm: vec![longest; n],
                friction_n: vec![[longest; 3]; n],
            };
            // Kept and left-out (or unreachable) vertices counted together: here as many of
            // each.
            let size = file.to_toml_string().len() as u64;
            let bound = GridFile::size_bound(2 * n, spec.len());
            assert!(size <= bound, "{dims:?}: {size} > {bound}");
        }
    }

    /// [`calibrated`] with an arm model chosen, as a calibration with an arm profile writes it.
    fn with_arm() -> GridFile {
        let mut file = calibrated();
        let gravity = crate::arm::tests::phantom_gravity();
        file.arm = Some(ArmRecord {
            rank: 4,
            unidentified: vec!["base, radial".into(), "base, lateral".into()],
            ..ArmRecord::new("phantom_1_5", &gravity)
        });
        file.model = Some(ModelRecord {
            chosen: "arm".into(),
            held_out_holds: 2,
            held_out_pct: HeldOutRecord {
                scalar: Some(48.0),
                vector: Some(9.3),
                arm: Some(0.13),
                arm_residual: None,
            },
            warning: None,
        });
        file
    }

    #[test]
    fn an_arm_model_is_format_2_and_round_trips_and_format_1_stays_1() {
        let file = with_arm();
        let text = file.to_toml_string();
        assert!(text.starts_with("format = \"hgcd-grid/2\"\n"), "{text}");
        assert_eq!(parse(&text).unwrap(), file);
        // Without an arm model the same file is written, and read, as version 1.
        let plain = calibrated().to_toml_string();
        assert!(plain.starts_with("format = \"hgcd-grid/1\"\n"));
        assert!(!plain.contains("[arm]") && !plain.contains("[model]"));
    }

    #[test]
    fn a_broken_arm_model_is_refused_with_what_is_wrong() {
        let text = with_arm().to_toml_string();
        // `from` replaced by `to` at its first place in or after the `[model]` table.
        let broken = |from: &str, to: &str| {
            let at = text.find("[model]").unwrap();
            let (head, tail) = text.split_at(at);
            assert!(tail.contains(from), "{from}");
            problem(&format!("{head}{}", tail.replacen(from, to, 1)))
        };
        let p = broken("parameters = [", "parameters = [0.1, ");
        assert!(p.to_string().contains("`parameters` has 7 values"), "{p}");
        let p = broken("upper_m = 0.215", "upper_m = 2.0");
        assert!(p.to_string().contains("`upper_m`"), "{p}");
        let p = broken("chosen = \"arm\"", "chosen = \"spline\"");
        assert_eq!(
            p,
            Problem::Model {
                chosen: "spline".into()
            }
        );
        let p = broken(
            "gravity_direction = [0.0, 0.0, 1.0]",
            "gravity_direction = [0.0, 0.0, 2.0]",
        );
        assert!(
            p.to_string().starts_with("`[arm]`: `gravity_direction`"),
            "{p}"
        );
        // An arm model chosen without its table.
        let mut file = with_arm();
        file.arm = None;
        assert_eq!(
            file.check(),
            Err(Problem::Model {
                chosen: "arm".into()
            })
        );
    }
}
