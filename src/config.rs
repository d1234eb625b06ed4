//! Typed configuration (`config/hgcd.toml` documents every key). Any subset of keys may be given;
//! the rest take their defaults. Unknown keys are rejected with the key's name; every numeric key
//! has a physically sane range ([`RANGES`]), checked by [`Config::validate`] on load, and a value
//! outside it is rejected with one line naming the key, the value and the range.
//! Units in the file are the ones users speak (mm, N/mm, ms); the accessors on each section are
//! the one place they are converted to SI (m, s, N/m).

use std::fmt;
use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::time::Duration;

use nalgebra::Vector3;
use serde::Deserialize;
use thiserror::Error;

use crate::estimate::FoawVariant;
use crate::protocol::{DeviceInfo, SERIAL_LEN};

/// Default configuration file of an installed daemon.
pub const DEFAULT_CONFIG_PATH: &str = "/etc/hgcd/hgcd.toml";
/// Default directory for calibration grids.
pub const DEFAULT_STATE_DIR: &str = "/var/lib/hgcd";

#[derive(Debug, Error)]
pub enum ConfigError {
    #[error("cannot read config file {path}: {error}")]
    Read {
        path: PathBuf,
        error: std::io::Error,
    },
    #[error("config file {path}: {message}")]
    Parse { path: PathBuf, message: String },
    #[error("config key `{key}`: {message}")]
    Invalid { key: String, message: String },
    #[error("config key `{key}`: {} is out of range ({range})", Number(*.value))]
    OutOfRange {
        key: &'static str,
        /// The value given (for an array key, the first element out of range).
        value: f64,
        range: Range,
    },
    #[error("device spec `{spec}`: {message}")]
    DeviceSpec { spec: String, message: String },
}

fn invalid(key: &str, message: impl Into<String>) -> ConfigError {
    ConfigError::Invalid {
        key: key.to_string(),
        message: message.into(),
    }
}

/// The closed interval a numeric key must lie in, in the unit the file uses.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Range {
    pub min: f64,
    pub max: f64,
    /// The file's unit; empty for counts and ratios.
    pub unit: &'static str,
}

impl Range {
    const fn new(min: f64, max: f64, unit: &'static str) -> Self {
        Self { min, max, unit }
    }

    /// Whether `value` lies in the range (never for NaN).
    pub fn contains(&self, value: f64) -> bool {
        value >= self.min && value <= self.max
    }
}

impl fmt::Display for Range {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} to {}", Number(self.min), Number(self.max))?;
        if !self.unit.is_empty() {
            write!(f, " {}", self.unit)?;
        }
        Ok(())
    }
}

/// A number as a user would write it in TOML: `1e308` rather than 309 digits, `nan`, `inf`.
/// A number as a message quotes it: `1e300` rather than three hundred digits, `nan`, `-inf`.
pub struct Number(pub f64);

impl fmt::Display for Number {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let v = self.0;
        let magnitude = v.abs();
        if v.is_nan() {
            write!(f, "nan")
        } else if v.is_infinite() {
            write!(f, "{}inf", if v < 0.0 { "-" } else { "" })
        } else if v != 0.0 && !(1e-4..1e9).contains(&magnitude) {
            write!(f, "{v:e}")
        } else {
            write!(f, "{v}")
        }
    }
}

/// A TOML file's error on one line: the line and its key, where the parser knows them, and what
/// is wrong.
pub fn toml_error(text: &str, error: &toml::de::Error) -> String {
    let message = error.message().trim().replace('\n', " ");
    let Some(span) = error.span() else {
        return message;
    };
    let before = &text[..span.start.min(text.len())];
    let line = before.matches('\n').count() + 1;
    let key = text
        .lines()
        .nth(line - 1)
        .and_then(|l| l.split_once('='))
        .map_or("", |(k, _)| k.trim());
    format!("line {line} (`{key}`): {message}")
}

/// Every numeric key and its range, in the file's units (`config/hgcd.toml` states each one; a
/// test pins them together). Array keys apply the range to each element. Cross-key rules (a
/// watchdog of at least two report periods, ordered workspace corners, ...) are checked on top.
pub const RANGES: &[(&str, Range)] = &[
    ("device.workspace_min_mm", Range::new(-1000.0, 1000.0, "mm")),
    ("device.workspace_max_mm", Range::new(-1000.0, 1000.0, "mm")),
    ("servo.rate_hz", Range::new(100.0, 10_000.0, "Hz")),
    ("servo.watchdog_ms", Range::new(1.0, 1000.0, "ms")),
    ("servo.realtime_priority", Range::new(0.0, 99.0, "")),
    (
        "servo.cpu",
        Range::new(-1.0, libc::CPU_SETSIZE as f64 - 1.0, ""),
    ),
    ("safety.max_force_n", Range::new(0.1, 50.0, "N")),
    (
        "safety.max_force_rate_n_per_s",
        Range::new(10.0, 100_000.0, "N/s"),
    ),
    ("estimate.noise_bound_mm", Range::new(1e-4, 1.0, "mm")),
    (
        "estimate.max_window",
        Range::new(1.0, crate::estimate::foaw::MAX_WINDOW as f64, "periods"),
    ),
    ("sim.mass_kg", Range::new(-10.0, 10.0, "kg")),
    ("sim.inertia_kg", Range::new(0.001, 10.0, "kg")),
    ("sim.g", Range::new(1.0, 30.0, "m/s^2")),
    ("sim.gravity_direction", Range::new(-1000.0, 1000.0, "")),
    ("sim.workspace_min_mm", Range::new(-1000.0, 1000.0, "mm")),
    ("sim.workspace_max_mm", Range::new(-1000.0, 1000.0, "mm")),
    ("sim.start_position_mm", Range::new(-1000.0, 1000.0, "mm")),
    ("sim.max_force_n", Range::new(0.1, 100.0, "N")),
    ("sim.encoder_resolution_mm", Range::new(0.0, 1.0, "mm")),
    ("sim.noise_mm", Range::new(0.0, 1.0, "mm")),
    ("sim.damping_n_s_per_m", Range::new(0.0, 100.0, "N*s/m")),
    ("sim.coulomb_friction_n", Range::new(0.0, 10.0, "N")),
    ("sim.spring_n_per_m", Range::new(0.0, 10_000.0, "N/m")),
    ("sim.spring_anchor_mm", Range::new(-1000.0, 1000.0, "mm")),
    ("sim.force_delay_ms", Range::new(0.0, 100.0, "ms")),
    ("sim.position_delay_ms", Range::new(0.0, 100.0, "ms")),
    ("sim.force_scale", Range::new(0.1, 10.0, "")),
    ("sim.cogging_n", Range::new(0.0, 10.0, "N")),
    ("sim.cogging_pitch_mm", Range::new(0.1, 1000.0, "mm")),
    ("sim.vibration_n", Range::new(0.0, 10.0, "N")),
    ("sim.vibration_hz", Range::new(0.1, 500.0, "Hz")),
    ("sim.probe_mass_kg", Range::new(0.0, 1.0, "kg")),
    ("sim.friction_scale", Range::new(0.0, 10.0, "")),
    ("sim.substep_hz", Range::new(100.0, 1e6, "Hz")),
    ("sim.device_watchdog_ms", Range::new(1.0, 1000.0, "ms")),
    ("sim.stop_reporting_after_s", Range::new(0.0, 1e6, "s")),
    ("sim.obstacle_min_mm", Range::new(-1000.0, 1000.0, "mm")),
    ("sim.obstacle_max_mm", Range::new(-1000.0, 1000.0, "mm")),
    ("calibration.spacing_mm", Range::new(1.0, 500.0, "mm")),
    ("calibration.half_size", Range::new(1.0, 10.0, "")),
    ("calibration.centre_mm", Range::new(-1000.0, 1000.0, "mm")),
    (
        "calibration.k_init_n_per_mm",
        Range::new(0.01, 20.0, "N/mm"),
    ),
    (
        "calibration.init_damping_n_s_per_m",
        Range::new(0.0, 100.0, "N*s/m"),
    ),
    ("calibration.n_init", Range::new(1.0, 10_000.0, "samples")),
    ("calibration.eps_init_mm", Range::new(0.001, 10.0, "mm")),
    ("calibration.n_m", Range::new(1.0, 10_000.0, "samples")),
    ("calibration.eps_m_mm", Range::new(0.001, 10.0, "mm")),
    ("calibration.g", Range::new(1.0, 30.0, "m/s^2")),
    ("calibration.rise_time_ms", Range::new(10.0, 10_000.0, "ms")),
    ("calibration.damping_ratio", Range::new(0.1, 10.0, "")),
    ("calibration.move_time_ms", Range::new(10.0, 60_000.0, "ms")),
    ("calibration.vertex_timeout_s", Range::new(0.1, 3600.0, "s")),
    ("calibration.max_iterations", Range::new(2.0, 1000.0, "")),
    (
        "compensation.auto_update_max_g",
        Range::new(0.0, 1000.0, "g"),
    ),
    (
        "compensation.auto_update_max_deg",
        Range::new(0.0, 30.0, "degrees"),
    ),
    ("app.stale_offset_ms", Range::new(1.0, 1000.0, "ms")),
    ("app.stale_ramp_ms", Range::new(1.0, 1000.0, "ms")),
    ("app.max_clients", Range::new(1.0, 1024.0, "")),
    ("app.hello_timeout_ms", Range::new(10.0, 60_000.0, "ms")),
    ("validation.point_spacing_mm", Range::new(1.0, 500.0, "mm")),
    (
        "validation.hold_stiffness_n_per_mm",
        Range::new(0.1, 10.0, "N/mm"),
    ),
    (
        "validation.surface_damping_n_s_per_m",
        Range::new(0.0, 100.0, "N*s/m"),
    ),
    ("validation.lift_mm", Range::new(0.5, 100.0, "mm")),
    ("validation.n_s", Range::new(2.0, 10_000.0, "samples")),
    ("validation.eps_s_mm", Range::new(0.001, 10.0, "mm")),
    ("validation.settle_timeout_s", Range::new(0.1, 3600.0, "s")),
    ("validation.up_direction", Range::new(-1000.0, 1000.0, "")),
    ("validation.drop_mm", Range::new(0.01, 50.0, "mm")),
    ("validation.dither_n", Range::new(0.0, 5.0, "N")),
    ("validation.dither_hz", Range::new(5.0, 200.0, "Hz")),
    ("validation.dither_s", Range::new(0.02, 10.0, "s")),
];

impl Range {
    /// The range of `key`, an entry of [`RANGES`].
    fn of(key: &str) -> Range {
        RANGES
            .iter()
            .find(|(k, _)| *k == key)
            .map(|(_, r)| *r)
            .unwrap_or_else(|| panic!("no range for config key {key}"))
    }
}

/// `value` checked against the range of `key` (an entry of [`RANGES`]).
fn in_range(key: &'static str, value: f64) -> Result<(), ConfigError> {
    let range = Range::of(key);
    if range.contains(value) {
        Ok(())
    } else {
        Err(ConfigError::OutOfRange { key, value, range })
    }
}

/// Every element of an array key checked against its range.
fn each_in_range(key: &'static str, values: [f64; 3]) -> Result<(), ConfigError> {
    values.iter().try_for_each(|v| in_range(key, *v))
}

/// Which device to open.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum DeviceSpec {
    /// A real device through hidapi, by USB vendor and product ID and optional serial number.
    Hid {
        vid: u16,
        pid: u16,
        serial: Option<String>,
    },
    /// The mock-HID backend around a simulated plant.
    Sim { model: String },
    /// Reports framed over a Unix stream socket (external simulator or hardware bridge).
    Socket { path: PathBuf },
}

/// Simulated plants `sim:MODEL` knows.
pub const SIM_MODELS: &[&str] = &["point-mass", "phantom", "delta", SIM_WOODENHAPTICS];
/// The simulated WoodenHaptics-protocol device (`sim:woodenhaptics`, a joint-space profile).
pub const SIM_WOODENHAPTICS: &str = "woodenhaptics";
/// Default directory of the user's device profiles (`NAME.toml`, `docs/devices.md`).
pub const DEFAULT_PROFILE_DIR: &str = "/etc/hgcd/profiles";

impl FromStr for DeviceSpec {
    type Err = ConfigError;
    fn from_str(spec: &str) -> Result<Self, ConfigError> {
        let err = |message: &str| ConfigError::DeviceSpec {
            spec: spec.to_string(),
            message: message.to_string(),
        };
        let (kind, rest) = spec
            .split_once(':')
            .ok_or_else(|| err("expected hid:VID:PID[:SERIAL], sim:MODEL or socket:PATH"))?;
        match kind {
            "hid" => {
                let mut parts = rest.splitn(3, ':');
                let hex = |p: Option<&str>, what: &str| {
                    let s = p.unwrap_or("");
                    u16::from_str_radix(s.trim_start_matches("0x"), 16)
                        .map_err(|_| err(&format!("{what} must be 4 hex digits, got `{s}`")))
                };
                let vid = hex(parts.next(), "VID")?;
                let pid = hex(parts.next(), "PID")?;
                let serial = parts.next().filter(|s| !s.is_empty()).map(str::to_string);
                Ok(DeviceSpec::Hid { vid, pid, serial })
            }
            "sim" => {
                if SIM_MODELS.contains(&rest) {
                    Ok(DeviceSpec::Sim {
                        model: rest.to_string(),
                    })
                } else {
                    Err(err(&format!(
                        "unknown simulated model; known: {}",
                        SIM_MODELS.join(", ")
                    )))
                }
            }
            "socket" if !rest.is_empty() => Ok(DeviceSpec::Socket {
                path: PathBuf::from(rest),
            }),
            _ => Err(err(
                "expected hid:VID:PID[:SERIAL], sim:MODEL or socket:PATH",
            )),
        }
    }
}

impl fmt::Display for DeviceSpec {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            DeviceSpec::Hid { vid, pid, serial } => {
                write!(f, "hid:{vid:04x}:{pid:04x}")?;
                if let Some(s) = serial {
                    write!(f, ":{s}")?;
                }
                Ok(())
            }
            DeviceSpec::Sim { model } => write!(f, "sim:{model}"),
            DeviceSpec::Socket { path } => write!(f, "socket:{}", path.display()),
        }
    }
}

/// `s` as part of a file name: ASCII letters, digits and `-` kept, anything else `_`.
pub fn id_part(s: &str) -> String {
    s.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' {
                c
            } else {
                '_'
            }
        })
        .collect()
}

impl DeviceSpec {
    /// Stable identity used to name the calibration file of a device that does not name itself
    /// (`<state_dir>/<id>.toml`; see `grid::DeviceIdentity` for one that does).
    pub fn device_id(&self) -> String {
        let clean = id_part;
        match self {
            DeviceSpec::Hid { vid, pid, serial } => match serial {
                Some(s) => format!("hid-{vid:04x}-{pid:04x}-{}", clean(s)),
                None => format!("hid-{vid:04x}-{pid:04x}"),
            },
            DeviceSpec::Sim { model } => format!("sim-{}", clean(model)),
            DeviceSpec::Socket { path } => format!(
                "socket-{}",
                clean(
                    &path
                        .file_name()
                        .map(|n| n.to_string_lossy())
                        .unwrap_or_default()
                )
            ),
        }
    }
}

/// Which gravity model compensation uses.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum CompensationMode {
    /// F_G = M(X) g v_G (paper Eq. 15).
    #[default]
    Scalar,
    /// F_G interpolated from the calibrated per-vertex force vectors.
    Vector,
    /// F_G = J⁻ᵀ τ_g of the arm model fitted at calibration (a profile with an arm).
    Arm,
    /// The arm model plus the vector lattice of what it left over at the vertices.
    ArmResidual,
}

impl std::str::FromStr for CompensationMode {
    type Err = String;

    /// The name [`Display`](std::fmt::Display) gives, as `compensation.mode` and a grid file's
    /// `[model] chosen` spell it.
    fn from_str(s: &str) -> Result<Self, String> {
        [Self::Scalar, Self::Vector, Self::Arm, Self::ArmResidual]
            .into_iter()
            .find(|m| m.to_string() == s)
            .ok_or_else(|| format!("unknown compensation mode `{s}`"))
    }
}

impl std::fmt::Display for CompensationMode {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Scalar => "scalar",
            Self::Vector => "vector",
            Self::Arm => "arm",
            Self::ArmResidual => "arm-residual",
        })
    }
}

/// Which workspace calibration covers.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum WorkspaceMode {
    /// The paper's cube of `half_size` and `spacing_mm` around `centre_mm`.
    #[default]
    Cube,
    /// Explore the reachable workspace from X_C first, then calibrate every vertex of the
    /// lattice inside it (docs/calibration.md §12).
    Explore,
}

impl std::str::FromStr for WorkspaceMode {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "cube" => Ok(Self::Cube),
            "explore" => Ok(Self::Explore),
            other => Err(format!("unknown workspace `{other}`: cube or explore")),
        }
    }
}

/// Which vertices of the cube a calibration holds the handle at.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum HoldPlan {
    /// `sparse` for a device whose profile has an arm, `all` otherwise.
    #[default]
    Auto,
    /// Every vertex (the paper).
    All,
    /// The cube's eight corners, farthest apart in joint angles: enough for the
    /// arm model's few parameters; the other vertices are filled from them.
    Sparse,
}

/// What compensation does outside the calibrated grid.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum OutsideGrid {
    /// Clamp the position onto the grid: the nearest cell's face values hold.
    #[default]
    HoldNearest,
    /// No gravity force outside the grid.
    Zero,
}

/// The keys a device's own description (its device-info report) stands in for when the file does
/// not give them ([`Config::for_device`]). A config built in code gives none of them unless it
/// says so here.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct GivenKeys {
    /// `device.workspace_min_mm` or `device.workspace_max_mm`.
    pub workspace: bool,
    /// `calibration.centre_mm`.
    pub centre: bool,
    /// `calibration.spacing_mm` or `calibration.half_size`: the size of the cube.
    pub cube: bool,
}

/// Share of each workspace half-extent left free around the calibration cube that
/// [`Config::for_device`] fits into a device's workspace.
pub const CUBE_MARGIN: f64 = 0.25;

/// The whole configuration.
#[derive(Clone, Debug, Default, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct Config {
    /// Which of the keys a device can stand in for the file gave (not a key itself).
    #[serde(skip)]
    pub given: GivenKeys,
    pub device: DeviceConfig,
    pub servo: ServoConfig,
    pub safety: SafetyConfig,
    pub estimate: EstimateConfig,
    pub sim: SimConfig,
    pub calibration: CalibrationConfig,
    pub compensation: CompensationConfig,
    pub app: AppConfig,
    pub paths: PathsConfig,
    pub validation: ValidationConfig,
}

#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct DeviceConfig {
    /// Device spec used when the command line gives none.
    pub spec: String,
    /// Device profile by name or path (`docs/devices.md`); empty: chosen by the device.
    pub profile: String,
    /// Box the handle may safely be driven in, mm, in the device frame (smallest corner).
    pub workspace_min_mm: [f64; 3],
    /// Largest corner of that box, mm.
    pub workspace_max_mm: [f64; 3],
}

impl Default for DeviceConfig {
    fn default() -> Self {
        Self {
            spec: "sim:point-mass".into(),
            profile: String::new(),
            workspace_min_mm: [-70.0; 3],
            workspace_max_mm: [70.0; 3],
        }
    }
}

#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct ServoConfig {
    /// Nominal report rate of the device, Hz.
    pub rate_hz: f64,
    /// No input report for this long is a fault: zero force, logged once. ms.
    pub watchdog_ms: f64,
    /// SCHED_FIFO priority 1–99 for the servo thread; 0 keeps normal scheduling.
    pub realtime_priority: u8,
    /// Pin the servo thread to this CPU; -1 leaves it unpinned.
    pub cpu: i32,
    /// Lock the process's memory (mlockall) so the loop never page-faults.
    pub lock_memory: bool,
}

impl Default for ServoConfig {
    fn default() -> Self {
        Self {
            rate_hz: 1000.0,
            watchdog_ms: 10.0,
            realtime_priority: 80,
            cpu: -1,
            lock_memory: true,
        }
    }
}

#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct SafetyConfig {
    /// Largest force magnitude ever sent to the device, N.
    pub max_force_n: f64,
    /// Largest rate of change of the force, N/s (zeroing on a fault is never rate-limited).
    pub max_force_rate_n_per_s: f64,
}

impl Default for SafetyConfig {
    fn default() -> Self {
        Self {
            max_force_n: 8.0,
            max_force_rate_n_per_s: 4000.0,
        }
    }
}

#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct EstimateConfig {
    /// FOAW variant: "end-fit" or "best-fit".
    pub foaw_variant: FoawVariant,
    /// Peak position measurement noise d, mm.
    pub noise_bound_mm: f64,
    /// Largest FOAW window, in sample periods (1–64).
    pub max_window: usize,
}

impl Default for EstimateConfig {
    fn default() -> Self {
        Self {
            foaw_variant: FoawVariant::BestFit,
            noise_bound_mm: 0.01,
            max_window: 16,
        }
    }
}

#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct SimConfig {
    /// Seed of the noise generator; equal seeds give identical runs.
    pub seed: u64,
    /// Serial number the simulated firmware reports in its device-info report; empty: none.
    pub serial: String,
    /// Mass field from an `hgcd-grid/1` file (its gravity_direction and g then apply); empty: uniform.
    pub mass_grid: Option<PathBuf>,
    /// Uniform apparent mass when no grid is given, kg: negative for an over-balanced handle that
    /// gravity (through its counterweight) pushes along v_G.
    pub mass_kg: f64,
    /// Moving mass the actuators accelerate, kg; unset: the magnitude of the apparent mass (at
    /// least 1 g). The probe mass adds to it.
    pub inertia_kg: Option<f64>,
    /// Gravitational acceleration, m/s².
    pub g: f64,
    /// Unit direction of the compensating force (opposite to gravity) when no grid is given.
    pub gravity_direction: [f64; 3],
    /// Hard workspace limits (mechanical stops), mm.
    pub workspace_min_mm: [f64; 3],
    pub workspace_max_mm: [f64; 3],
    /// Where the handle rests when the device starts, mm.
    pub start_position_mm: [f64; 3],
    /// Actuator force limit per axis, N.
    pub max_force_n: f64,
    /// Encoder resolution, mm (0 disables quantisation).
    pub encoder_resolution_mm: f64,
    /// Standard deviation of Gaussian position noise, mm (0 disables noise).
    pub noise_mm: f64,
    /// Viscous friction at the handle, N·s/m (on top of a linkage's joint friction).
    pub damping_n_s_per_m: f64,
    /// Coulomb friction at the handle, N: the handle sticks while the net force on it is at most
    /// this, and slides against this much force otherwise.
    pub coulomb_friction_n: f64,
    /// An isotropic spring pulling the handle toward `spring_anchor_mm` (a cable, a hose), N/m.
    pub spring_n_per_m: f64,
    pub spring_anchor_mm: [f64; 3],
    /// The actuators render each force command this much later, ms (whole report periods): a
    /// slow amplifier or a buffered driver.
    pub force_delay_ms: f64,
    /// Each input report carries the position (`sim:woodenhaptics`: the joint counts) measured
    /// this much earlier, ms (whole report periods): a slow encoder interface or a filtering
    /// sensor.
    pub position_delay_ms: f64,
    /// Protocol v1 devices (refused by `sim:woodenhaptics`): each axis's actuators render this
    /// share of the commanded force (an amplifier's gain or a motor constant off).
    pub force_scale: [f64; 3],
    /// Protocol v1 devices (refused by `sim:woodenhaptics`): motor cogging, a force `cogging_n`
    /// sin(2π x_i / pitch) along each axis i, of the position alone and in no candidate of
    /// `hgcd analyze`, N.
    pub cogging_n: f64,
    pub cogging_pitch_mm: f64,
    /// Protocol v1 devices (refused by `sim:woodenhaptics`): the table vibrates (a pump, a fan):
    /// a force `vibration_n` along (1, 1, 1)/√3 at `vibration_hz`, of time alone and in no
    /// candidate of `hgcd analyze`, N.
    pub vibration_n: f64,
    pub vibration_hz: f64,
    /// Probe mass attached to the end effector, kg (the paper's validation uses 30 g).
    pub probe_mass_kg: f64,
    /// Linkage plants: which unit of the model (0: the nominal published one; any other value a
    /// unit whose masses, centres of mass and friction differ by a few percent).
    pub unit_seed: u64,
    /// Linkage plants: multiplies every joint friction coefficient (0: frictionless).
    pub friction_scale: f64,
    /// Integration rate, Hz (at least the report rate; 10 kHz or more keeps the physics accurate).
    pub substep_hz: f64,
    /// The device zeroes force when no output report arrives for this long, ms.
    pub device_watchdog_ms: f64,
    /// Fault injection: the device stops reporting after this much device time, s.
    pub stop_reporting_after_s: Option<f64>,
    /// A box the handle cannot enter (an obstacle, a wall the user did not declare), mm; both
    /// corners or neither. Every plant honours it.
    pub obstacle_min_mm: Option<[f64; 3]>,
    pub obstacle_max_mm: Option<[f64; 3]>,
}

impl Default for SimConfig {
    fn default() -> Self {
        Self {
            seed: 1,
            serial: String::new(),
            mass_grid: None,
            mass_kg: 0.12,
            inertia_kg: None,
            g: 9.81,
            gravity_direction: [0.0, 0.0, 1.0],
            workspace_min_mm: [-80.0; 3],
            workspace_max_mm: [80.0; 3],
            start_position_mm: [0.0; 3],
            max_force_n: 10.0,
            encoder_resolution_mm: 0.005,
            noise_mm: 0.002,
            damping_n_s_per_m: 0.0,
            coulomb_friction_n: 0.0,
            spring_n_per_m: 0.0,
            spring_anchor_mm: [0.0; 3],
            force_delay_ms: 0.0,
            position_delay_ms: 0.0,
            force_scale: [1.0; 3],
            cogging_n: 0.0,
            cogging_pitch_mm: 5.0,
            vibration_n: 0.0,
            vibration_hz: 7.0,
            probe_mass_kg: 0.0,
            unit_seed: 0,
            friction_scale: 1.0,
            substep_hz: 10_000.0,
            device_watchdog_ms: 50.0,
            stop_reporting_after_s: None,
            obstacle_min_mm: None,
            obstacle_max_mm: None,
        }
    }
}

#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct CalibrationConfig {
    /// Cube side L, mm.
    pub spacing_mm: f64,
    /// N: vertices (nL, mL, pL) with n, m, p in [−N, N].
    pub half_size: u32,
    /// Grid centre in the device frame, mm.
    pub centre_mm: [f64; 3],
    /// Stiffness of the initial holding field, N/mm.
    pub k_init_n_per_mm: f64,
    /// Damping added to the initial field, N·s/m (beyond the paper; 0 for the paper's pure spring).
    pub init_damping_n_s_per_m: f64,
    /// Consecutive samples for the initial steady state.
    pub n_init: usize,
    /// Radius of the initial steady-state sphere, mm.
    pub eps_init_mm: f64,
    /// Consecutive samples for a vertex steady state.
    pub n_m: usize,
    /// Radius of the vertex steady-state sphere and of the convergence test, mm.
    pub eps_m_mm: f64,
    /// Gravitational acceleration, m/s².
    pub g: f64,
    /// 10–90 % rise time of the linearised closed loop, ms (sets β).
    pub rise_time_ms: f64,
    /// Damping ratio of the linearised closed loop (sets α with β).
    pub damping_ratio: f64,
    /// Duration of the smooth move between vertices, ms.
    pub move_time_ms: f64,
    /// A vertex that has not converged after this long fails the calibration, s.
    pub vertex_timeout_s: f64,
    /// Largest number of mass updates at one vertex.
    pub max_iterations: u32,
    /// "cube" (the paper's grid) or "explore" (the reachable workspace, found first).
    pub workspace: WorkspaceMode,
    /// "auto", "all" or "sparse": which of the cube's vertices are held.
    pub holds: HoldPlan,
}

impl Default for CalibrationConfig {
    fn default() -> Self {
        Self {
            spacing_mm: 40.0,
            half_size: 1,
            centre_mm: [0.0; 3],
            k_init_n_per_mm: 0.5,
            init_damping_n_s_per_m: 5.0,
            n_init: 30,
            eps_init_mm: 0.1,
            n_m: 30,
            eps_m_mm: 0.1,
            g: 9.81,
            rise_time_ms: 100.0,
            damping_ratio: 1.0,
            move_time_ms: 400.0,
            vertex_timeout_s: 10.0,
            max_iterations: 20,
            workspace: WorkspaceMode::Cube,
            holds: HoldPlan::Auto,
        }
    }
}

#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct CompensationConfig {
    /// "scalar" (paper: M(X) g v_G), "vector" (interpolated calibrated force vectors), "arm"
    /// (the arm model fitted at calibration) or "arm-residual" (arm plus the lattice of what it
    /// left); unset: the model the calibration chose by its held-out score, else vector when the
    /// grid has force vectors (every grid calibration writes does), else scalar.
    pub mode: Option<CompensationMode>,
    /// Outside the grid: "hold-nearest" (nearest cell's face values) or "zero".
    pub outside_grid: OutsideGrid,
    /// Run without compensation when the grid is corrupt or made for another device (a missing
    /// grid always runs uncompensated, so the device can be calibrated through the daemon).
    pub allow_uncompensated: bool,
    /// An `hgcd-model/1` file (`hgcd analyze`'s model.toml): its effect is added to the grid's
    /// compensation when it is a force of the position alone (payload, gravity tilt, spring).
    pub effect_file: Option<PathBuf>,
    /// A payload the daemon notices in use on a released handle (one that keeps sinking or
    /// rising, docs/calibration.md §2.3) is taken into the compensation it runs, not only
    /// reported. One shown by an application's offsets is only reported.
    pub auto_update: bool,
    /// The largest payload `auto_update` takes in, g (either sign); one beyond is only reported.
    pub auto_update_max_g: f64,
    /// The largest tilt `auto_update` takes in, degrees; one beyond is only reported (and with
    /// it the payload).
    pub auto_update_max_deg: f64,
}

impl Default for CompensationConfig {
    fn default() -> Self {
        Self {
            mode: None,
            outside_grid: OutsideGrid::default(),
            allow_uncompensated: false,
            effect_file: None,
            auto_update: false,
            auto_update_max_g: 50.0,
            auto_update_max_deg: 5.0,
        }
    }
}

#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct AppConfig {
    /// Application socket; default: one per device, `<runtime dir>/<device-id>.sock`
    /// (`app::endpoint`).
    pub socket: Option<PathBuf>,
    /// Permissions of the socket file (octal, as a string).
    pub socket_mode: String,
    /// A force offset not refreshed for this long ramps to zero, ms.
    pub stale_offset_ms: f64,
    /// Duration of that ramp from the full offset to zero, ms.
    pub stale_ramp_ms: f64,
    /// Most clients connected at once; one more may still ask for status, further ones are refused.
    pub max_clients: usize,
    /// A client that has not said hello within this time is closed, ms.
    pub hello_timeout_ms: f64,
}

impl Default for AppConfig {
    fn default() -> Self {
        Self {
            socket: None,
            socket_mode: "0660".into(),
            stale_offset_ms: 50.0,
            stale_ramp_ms: 50.0,
            max_clients: 16,
            hello_timeout_ms: 5000.0,
        }
    }
}

#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct PathsConfig {
    /// Where calibration grids live (default: [`Config::state_dir`]).
    pub state_dir: Option<PathBuf>,
    /// Where the user's device profiles are (default: `profiles/` beside the config file, else
    /// [`DEFAULT_PROFILE_DIR`]).
    pub profile_dir: Option<PathBuf>,
}

#[allow(clippy::derivable_impls)]
impl Default for PathsConfig {
    fn default() -> Self {
        Self {
            state_dir: None,
            profile_dir: None,
        }
    }
}

/// The validation experiment's procedure (`hgcd validate`, docs/validation.md); the paper's own
/// parameters (probe mass, stiffness, repetitions) are command-line options.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct ValidationConfig {
    /// Contact points lie at the grid centre + spacing·(i, j, k), i, j, k in {−1, 0, 1}, mm.
    pub point_spacing_mm: f64,
    /// Stiffness of the application's hold (lifting, lowering, and across the surface), N/mm.
    pub hold_stiffness_n_per_mm: f64,
    /// Damping of the virtual surface while the handle is in it, N·s/m.
    pub surface_damping_n_s_per_m: f64,
    /// Height above the surface the handle is lifted to between repetitions, mm.
    pub lift_mm: f64,
    /// How far the surface drops, and rises back, before the reading from below, mm: more than
    /// twice the friction force over the surface stiffness.
    pub drop_mm: f64,
    /// Amplitude of the vibration that frees the handle from static friction for each reading,
    /// which is then the handle's mean position under it, per direction, N: above the friction
    /// at the handle. 0: none (the paper's procedure: the steady state's rest).
    pub dither_n: f64,
    /// Its frequency along the surface normal, Hz; the two directions across the surface
    /// vibrate at 1.23 and 1.51 times this.
    pub dither_hz: f64,
    /// How long it lasts, s, in three equal parts: the handle finds its equilibrium, its mean
    /// position is read, the vibration fades out.
    pub dither_s: f64,
    /// Steady state: samples per window, n_s (without a dither; with one, `eps_s_mm` alone
    /// bounds how far its reading window's two halves may disagree).
    pub n_s: usize,
    /// Steady state: radius of the window's sphere, eps_s, mm.
    pub eps_s_mm: f64,
    /// A repetition with no steady state after this long is recorded as unsettled, s.
    pub settle_timeout_s: f64,
    /// "Up" in the device frame, opposite to gravity: the surface's normal. Unset: on a simulated
    /// device its world's up, on hardware the grid's v_G.
    pub up_direction: Option<[f64; 3]>,
}

impl Default for ValidationConfig {
    fn default() -> Self {
        Self {
            point_spacing_mm: 30.0,
            hold_stiffness_n_per_mm: 1.0,
            surface_damping_n_s_per_m: 10.0,
            lift_mm: 5.0,
            drop_mm: 1.0,
            dither_n: 0.3,
            dither_hz: 50.0,
            dither_s: 1.2,
            n_s: 50,
            eps_s_mm: 0.05,
            settle_timeout_s: 5.0,
            up_direction: None,
        }
    }
}

impl ValidationConfig {
    /// Spacing of the contact points, m.
    pub fn point_spacing(&self) -> f64 {
        self.point_spacing_mm * 1e-3
    }

    /// Stiffness of the hold, N/m.
    pub fn hold_stiffness(&self) -> f64 {
        self.hold_stiffness_n_per_mm * 1e3
    }

    /// Lift height, m.
    pub fn lift(&self) -> f64 {
        self.lift_mm * 1e-3
    }

    /// The surface's drop before the reading from below, m.
    pub fn drop(&self) -> f64 {
        self.drop_mm * 1e-3
    }

    /// Radius of the steady-state sphere, m.
    pub fn eps_s(&self) -> f64 {
        self.eps_s_mm * 1e-3
    }
}

/// A point given in mm, in m.
fn mm(v: [f64; 3]) -> Vector3<f64> {
    Vector3::from(v) * 1e-3
}

/// A box given by its corners in mm, in m.
fn mm_box(lo: [f64; 3], hi: [f64; 3]) -> (Vector3<f64>, Vector3<f64>) {
    (mm(lo), mm(hi))
}

/// Two corners in range, each minimum below its maximum.
fn ordered_box(
    min_key: &'static str,
    max_key: &'static str,
    lo: [f64; 3],
    hi: [f64; 3],
) -> Result<(), ConfigError> {
    each_in_range(min_key, lo)?;
    each_in_range(max_key, hi)?;
    match (0..3).find(|&a| lo[a] >= hi[a]) {
        None => Ok(()),
        Some(a) => Err(invalid(
            max_key,
            format!(
                "{} is not above {min_key}'s {} on the {} axis; each maximum must exceed its minimum",
                Number(hi[a]),
                Number(lo[a]),
                ["x", "y", "z"][a]
            ),
        )),
    }
}

/// A duration key (ms) that must cover at least two report periods at `servo.rate_hz`.
fn two_periods(key: &str, value_ms: f64, rate_hz: f64) -> Result<(), ConfigError> {
    let least_ms = 2.0 * 1e3 / rate_hz;
    if value_ms >= least_ms {
        Ok(())
    } else {
        Err(invalid(
            key,
            format!(
                "{} ms is shorter than two report periods ({} ms at servo.rate_hz = {})",
                Number(value_ms),
                Number(least_ms),
                Number(rate_hz)
            ),
        ))
    }
}

impl DeviceConfig {
    /// The safe workspace box (smallest corner, largest corner), m.
    pub fn workspace(&self) -> (Vector3<f64>, Vector3<f64>) {
        mm_box(self.workspace_min_mm, self.workspace_max_mm)
    }
}

impl ServoConfig {
    /// Nominal report period, s.
    pub fn period(&self) -> f64 {
        1.0 / self.rate_hz
    }

    /// Silence that counts as a device fault, s.
    pub fn watchdog(&self) -> f64 {
        self.watchdog_ms * 1e-3
    }
}

impl EstimateConfig {
    /// Peak position measurement noise d, m.
    pub fn noise_bound(&self) -> f64 {
        self.noise_bound_mm * 1e-3
    }
}

impl SimConfig {
    /// The mechanical stops (smallest corner, largest corner), m.
    pub fn workspace(&self) -> (Vector3<f64>, Vector3<f64>) {
        mm_box(self.workspace_min_mm, self.workspace_max_mm)
    }

    /// Rest position at start, m.
    pub fn start_position(&self) -> Vector3<f64> {
        mm(self.start_position_mm)
    }

    /// Encoder resolution, m (0: no quantisation).
    pub fn encoder_resolution(&self) -> f64 {
        self.encoder_resolution_mm * 1e-3
    }

    pub fn spring_anchor(&self) -> Vector3<f64> {
        mm(self.spring_anchor_mm)
    }

    /// The actuators' delay, s.
    pub fn force_delay(&self) -> f64 {
        self.force_delay_ms * 1e-3
    }

    /// The position sensing's delay, s.
    pub fn position_delay(&self) -> f64 {
        self.position_delay_ms * 1e-3
    }

    /// The obstacle box (smallest corner, largest corner), m, if both corners are given.
    pub fn obstacle(&self) -> Option<(Vector3<f64>, Vector3<f64>)> {
        Some(mm_box(self.obstacle_min_mm?, self.obstacle_max_mm?))
    }

    /// Standard deviation of the position noise, m (0: none).
    pub fn noise(&self) -> f64 {
        self.noise_mm * 1e-3
    }

    /// Output-report silence after which the simulated firmware zeroes force, s.
    pub fn device_watchdog(&self) -> f64 {
        self.device_watchdog_ms * 1e-3
    }
}

impl CalibrationConfig {
    /// Cube side L, m.
    pub fn spacing(&self) -> f64 {
        self.spacing_mm * 1e-3
    }

    /// Grid centre, m.
    pub fn centre(&self) -> Vector3<f64> {
        mm(self.centre_mm)
    }

    /// Stiffness of the initial holding field, N/m.
    pub fn k_init(&self) -> f64 {
        self.k_init_n_per_mm * 1e3
    }

    /// Radius of the initial steady-state sphere, m.
    pub fn eps_init(&self) -> f64 {
        self.eps_init_mm * 1e-3
    }

    /// Radius of the vertex steady-state sphere and of the convergence test, m.
    pub fn eps_m(&self) -> f64 {
        self.eps_m_mm * 1e-3
    }

    /// 10–90 % rise time of the linearised closed loop, s.
    pub fn rise_time(&self) -> f64 {
        self.rise_time_ms * 1e-3
    }

    /// Duration of a one-cell move, s.
    pub fn move_time(&self) -> f64 {
        self.move_time_ms * 1e-3
    }
}

impl AppConfig {
    /// Age at which a force offset starts ramping to zero, s.
    pub fn stale_offset(&self) -> f64 {
        self.stale_offset_ms * 1e-3
    }

    /// Duration of the ramp from a stale offset to zero, s.
    pub fn stale_ramp(&self) -> f64 {
        self.stale_ramp_ms * 1e-3
    }

    /// Time a client has to say hello. A validated config gives 10 ms to 60 s (an unchecked
    /// value outside what `Duration` holds panics).
    pub fn hello_timeout(&self) -> Duration {
        Duration::from_secs_f64(self.hello_timeout_ms * 1e-3)
    }
}

impl Config {
    /// Parse and validate TOML text; `origin` names the source in messages.
    ///
    /// Errors: [`ConfigError::Parse`] for TOML or type errors and unknown keys, `OutOfRange`,
    /// `Invalid` or `DeviceSpec` for a value the checks refuse.
    pub fn from_toml_str(text: &str, origin: &Path) -> Result<Self, ConfigError> {
        let mut config: Config = toml::from_str(text).map_err(|e| ConfigError::Parse {
            path: origin.to_path_buf(),
            message: e.to_string().trim().replace('\n', " "),
        })?;
        let table: toml::Table = toml::from_str(text).unwrap_or_default();
        let has = |section: &str, keys: &[&str]| {
            table
                .get(section)
                .and_then(toml::Value::as_table)
                .is_some_and(|t| keys.iter().any(|k| t.contains_key(*k)))
        };
        config.given = GivenKeys {
            workspace: has("device", &["workspace_min_mm", "workspace_max_mm"]),
            centre: has("calibration", &["centre_mm"]),
            cube: has("calibration", &["spacing_mm", "half_size"]),
        };
        config.validate()?;
        Ok(config)
    }

    /// Load a config file.
    ///
    /// Errors: [`ConfigError::Read`] when the file cannot be read, then as
    /// [`Config::from_toml_str`].
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        let text = crate::sys::read_text(path).map_err(|error| ConfigError::Read {
            path: path.to_path_buf(),
            error,
        })?;
        let mut config = Self::from_toml_str(&text, path)?;
        // A relative mass-grid path is relative to the config file, not to the working directory.
        if let (Some(grid), Some(dir)) = (&config.sim.mass_grid, path.parent()) {
            if grid.is_relative() {
                config.sim.mass_grid = Some(dir.join(grid));
            }
        }
        // The user's profiles are beside the config file unless it says otherwise.
        if config.paths.profile_dir.is_none() {
            config.paths.profile_dir = path.parent().map(|dir| dir.join("profiles"));
        }
        Ok(config)
    }

    /// Check every value against its range ([`RANGES`]) and the cross-key rules; the first
    /// failure is returned as one line naming the key, the value and what is allowed. A config
    /// built in code should pass here before it runs anything ([`crate::daemon::Daemon::run`]
    /// and [`crate::calibrate::calibrate`] check).
    pub fn validate(&self) -> Result<(), ConfigError> {
        self.device_spec()?;
        let d = &self.device;
        ordered_box(
            "device.workspace_min_mm",
            "device.workspace_max_mm",
            d.workspace_min_mm,
            d.workspace_max_mm,
        )?;

        let s = &self.servo;
        in_range("servo.rate_hz", s.rate_hz)?;
        in_range("servo.watchdog_ms", s.watchdog_ms)?;
        two_periods("servo.watchdog_ms", s.watchdog_ms, s.rate_hz)?;
        in_range("servo.realtime_priority", s.realtime_priority.into())?;
        in_range("servo.cpu", s.cpu.into())?;

        in_range("safety.max_force_n", self.safety.max_force_n)?;
        in_range(
            "safety.max_force_rate_n_per_s",
            self.safety.max_force_rate_n_per_s,
        )?;

        in_range("estimate.noise_bound_mm", self.estimate.noise_bound_mm)?;
        in_range("estimate.max_window", self.estimate.max_window as f64)?;

        let sim = &self.sim;
        in_range("sim.mass_kg", sim.mass_kg)?;
        if let Some(m) = sim.inertia_kg {
            in_range("sim.inertia_kg", m)?;
        }
        in_range("sim.g", sim.g)?;
        each_in_range("sim.gravity_direction", sim.gravity_direction)?;
        if Vector3::from(sim.gravity_direction).norm() < 1e-6 {
            return Err(invalid(
                "sim.gravity_direction",
                "must not be the zero vector: give the direction opposite to gravity, e.g. [0.0, 0.0, 1.0]",
            ));
        }
        ordered_box(
            "sim.workspace_min_mm",
            "sim.workspace_max_mm",
            sim.workspace_min_mm,
            sim.workspace_max_mm,
        )?;
        each_in_range("sim.start_position_mm", sim.start_position_mm)?;
        in_range("sim.max_force_n", sim.max_force_n)?;
        in_range("sim.encoder_resolution_mm", sim.encoder_resolution_mm)?;
        in_range("sim.noise_mm", sim.noise_mm)?;
        in_range("sim.damping_n_s_per_m", sim.damping_n_s_per_m)?;
        in_range("sim.coulomb_friction_n", sim.coulomb_friction_n)?;
        in_range("sim.spring_n_per_m", sim.spring_n_per_m)?;
        each_in_range("sim.spring_anchor_mm", sim.spring_anchor_mm)?;
        in_range("sim.force_delay_ms", sim.force_delay_ms)?;
        in_range("sim.position_delay_ms", sim.position_delay_ms)?;
        each_in_range("sim.force_scale", sim.force_scale)?;
        in_range("sim.cogging_n", sim.cogging_n)?;
        in_range("sim.cogging_pitch_mm", sim.cogging_pitch_mm)?;
        in_range("sim.vibration_n", sim.vibration_n)?;
        in_range("sim.vibration_hz", sim.vibration_hz)?;
        in_range("sim.probe_mass_kg", sim.probe_mass_kg)?;
        in_range("sim.friction_scale", sim.friction_scale)?;
        in_range("sim.substep_hz", sim.substep_hz)?;
        if sim.substep_hz < s.rate_hz {
            return Err(invalid(
                "sim.substep_hz",
                format!(
                    "{} Hz is below servo.rate_hz ({} Hz): the plant must be integrated at least once per report",
                    Number(sim.substep_hz),
                    Number(s.rate_hz)
                ),
            ));
        }
        in_range("sim.device_watchdog_ms", sim.device_watchdog_ms)?;
        two_periods("sim.device_watchdog_ms", sim.device_watchdog_ms, s.rate_hz)?;
        if let Some(t) = sim.stop_reporting_after_s {
            in_range("sim.stop_reporting_after_s", t)?;
        }
        if sim.serial.len() > SERIAL_LEN || sim.serial.chars().any(char::is_control) {
            return Err(invalid(
                "sim.serial",
                format!(
                    "{:?} is not a serial number the device-info report carries: at most \
                     {SERIAL_LEN} bytes of text without control characters",
                    sim.serial
                ),
            ));
        }
        if let Some(lo) = sim.obstacle_min_mm {
            each_in_range("sim.obstacle_min_mm", lo)?;
        }
        if let Some(hi) = sim.obstacle_max_mm {
            each_in_range("sim.obstacle_max_mm", hi)?;
        }
        match (sim.obstacle_min_mm, sim.obstacle_max_mm) {
            (None, None) => {}
            (Some(lo), Some(hi)) => {
                ordered_box("sim.obstacle_min_mm", "sim.obstacle_max_mm", lo, hi)?
            }
            (Some(_), None) => {
                return Err(invalid(
                    "sim.obstacle_max_mm",
                    "missing: an obstacle needs both corners (sim.obstacle_min_mm is given)",
                ))
            }
            (None, Some(_)) => {
                return Err(invalid(
                    "sim.obstacle_min_mm",
                    "missing: an obstacle needs both corners (sim.obstacle_max_mm is given)",
                ))
            }
        }

        let c = &self.calibration;
        in_range("calibration.spacing_mm", c.spacing_mm)?;
        in_range("calibration.half_size", c.half_size.into())?;
        each_in_range("calibration.centre_mm", c.centre_mm)?;
        in_range("calibration.k_init_n_per_mm", c.k_init_n_per_mm)?;
        in_range(
            "calibration.init_damping_n_s_per_m",
            c.init_damping_n_s_per_m,
        )?;
        in_range("calibration.n_init", c.n_init as f64)?;
        in_range("calibration.eps_init_mm", c.eps_init_mm)?;
        in_range("calibration.n_m", c.n_m as f64)?;
        in_range("calibration.eps_m_mm", c.eps_m_mm)?;
        in_range("calibration.g", c.g)?;
        in_range("calibration.rise_time_ms", c.rise_time_ms)?;
        let least_rise_ms = 10.0 * 1e3 / s.rate_hz;
        if c.rise_time_ms < least_rise_ms {
            return Err(invalid(
                "calibration.rise_time_ms",
                format!(
                    "{} ms is shorter than ten report periods ({} ms at servo.rate_hz = {}): the sampled loop would not follow it",
                    Number(c.rise_time_ms),
                    Number(least_rise_ms),
                    Number(s.rate_hz)
                ),
            ));
        }
        in_range("calibration.damping_ratio", c.damping_ratio)?;
        in_range("calibration.move_time_ms", c.move_time_ms)?;
        in_range("calibration.vertex_timeout_s", c.vertex_timeout_s)?;
        in_range("calibration.max_iterations", c.max_iterations.into())?;

        in_range(
            "compensation.auto_update_max_g",
            self.compensation.auto_update_max_g,
        )?;
        in_range(
            "compensation.auto_update_max_deg",
            self.compensation.auto_update_max_deg,
        )?;

        let a = &self.app;
        self.socket_mode()?;
        in_range("app.stale_offset_ms", a.stale_offset_ms)?;
        two_periods("app.stale_offset_ms", a.stale_offset_ms, s.rate_hz)?;
        in_range("app.stale_ramp_ms", a.stale_ramp_ms)?;
        in_range("app.max_clients", a.max_clients as f64)?;
        in_range("app.hello_timeout_ms", a.hello_timeout_ms)?;

        let v = &self.validation;
        in_range("validation.point_spacing_mm", v.point_spacing_mm)?;
        in_range(
            "validation.hold_stiffness_n_per_mm",
            v.hold_stiffness_n_per_mm,
        )?;
        in_range(
            "validation.surface_damping_n_s_per_m",
            v.surface_damping_n_s_per_m,
        )?;
        in_range("validation.lift_mm", v.lift_mm)?;
        in_range("validation.drop_mm", v.drop_mm)?;
        in_range("validation.dither_n", v.dither_n)?;
        in_range("validation.dither_hz", v.dither_hz)?;
        in_range("validation.dither_s", v.dither_s)?;
        if v.dither_n > 0.0 {
            // The reading window (a third) holds enough periods to average the vibration out
            // (the servo rate is checked where the experiment runs: `validate::prepare`).
            if v.dither_s / 3.0 * v.dither_hz < 5.0 {
                return Err(invalid(
                    "validation.dither_s",
                    format!(
                        "{} s leaves its reading window (a third) under five periods at \
                         validation.dither_hz = {}: the mean would not average the vibration out",
                        Number(v.dither_s),
                        Number(v.dither_hz)
                    ),
                ));
            }
        }
        in_range("validation.n_s", v.n_s as f64)?;
        in_range("validation.eps_s_mm", v.eps_s_mm)?;
        in_range("validation.settle_timeout_s", v.settle_timeout_s)?;
        if let Some(up) = v.up_direction {
            each_in_range("validation.up_direction", up)?;
            if Vector3::from(up).norm() < 1e-6 {
                return Err(invalid(
                    "validation.up_direction",
                    "must not be the zero vector: give the direction opposite to gravity, e.g. [0.0, 0.0, 1.0]",
                ));
            }
        }
        Ok(())
    }

    /// This config with what the device said about itself (`info`, its device-info report)
    /// standing in for the keys the file did not give ([`GivenKeys`]): the safe box becomes the
    /// device's workspace, the calibration grid is centred in that box, and the cube's spacing
    /// shrinks from its configured value, if need be, until the cube fits inside the box with
    /// [`CUBE_MARGIN`] of each half-extent to spare. The host's force limit becomes the smaller
    /// of `safety.max_force_n` and the device's own (the host clamps too, rather than leave it
    /// to the device). Without `info`, the config as it is.
    pub fn for_device(&self, info: Option<&DeviceInfo>) -> Config {
        let mut config = self.clone();
        let Some(info) = info else {
            return config;
        };
        config.safety.max_force_n = config.safety.max_force_n.min(info.max_force);
        // To the nanometre, in mm: what the report carried, without binary-fraction noise.
        let mm = |v: Vector3<f64>| -> [f64; 3] { (v * 1e9).map(|nm| nm.round() / 1e6).into() };
        if !self.given.workspace {
            let (lo, hi) = info.workspace();
            config.device.workspace_min_mm = mm(lo);
            config.device.workspace_max_mm = mm(hi);
        }
        if !self.given.centre {
            config.calibration.centre_mm = mm(info.workspace_centre);
        }
        if !self.given.cube {
            let (lo, hi) = config.device.workspace();
            let centre = config.calibration.centre();
            let spare = (hi - lo) / 2.0 * CUBE_MARGIN;
            let room = (centre - lo - spare).inf(&(hi - spare - centre)).min() * 1e3;
            let fits = room / f64::from(config.calibration.half_size);
            // A centre the file put outside the box: nothing fits; the plan says so.
            if fits > 0.0 && fits < config.calibration.spacing_mm {
                let least = Range::of("calibration.spacing_mm").min;
                config.calibration.spacing_mm = ((fits * 1e6).floor() / 1e6).max(least);
            }
        }
        config
    }

    /// Where the user's device profiles are (`paths.profile_dir`).
    pub fn profile_dir(&self) -> PathBuf {
        self.paths
            .profile_dir
            .clone()
            .unwrap_or_else(|| PathBuf::from(DEFAULT_PROFILE_DIR))
    }

    /// The configured device spec.
    ///
    /// Errors: [`ConfigError::DeviceSpec`] when `device.spec` does not parse.
    pub fn device_spec(&self) -> Result<DeviceSpec, ConfigError> {
        self.device.spec.parse()
    }

    /// Nominal servo period, s.
    pub fn servo_period(&self) -> f64 {
        self.servo.period()
    }

    /// The socket file's permission bits.
    ///
    /// Errors: [`ConfigError::Invalid`] when `app.socket_mode` is not octal up to 0777.
    pub fn socket_mode(&self) -> Result<u32, ConfigError> {
        u32::from_str_radix(self.app.socket_mode.trim_start_matches("0o"), 8)
            .ok()
            .filter(|m| *m <= 0o777)
            .ok_or_else(|| {
                invalid(
                    "app.socket_mode",
                    "must be octal permission bits such as \"0660\"",
                )
            })
    }

    /// Calibration state directory, the first of: the config's `paths.state_dir` (which
    /// `--state-dir` sets); `$STATE_DIRECTORY` (systemd); /var/lib/hgcd when this user may
    /// create files there (root, user hgcd); else this user's own `$XDG_STATE_HOME/hgcd`
    /// (`~/.local/state/hgcd`). Every command of one user picks the same directory, so `hgcd run`
    /// finds the grid `hgcd calibrate` wrote, with or without root.
    pub fn state_dir(&self) -> PathBuf {
        if let Some(dir) = &self.paths.state_dir {
            return dir.clone();
        }
        if let Ok(dirs) = std::env::var("STATE_DIRECTORY") {
            // systemd passes a colon-separated list when several are configured.
            if let Some(first) = dirs.split(':').find(|s| !s.is_empty()) {
                return PathBuf::from(first);
            }
        }
        let system = Path::new(DEFAULT_STATE_DIR);
        default_state_dir(
            system,
            may_create_in(system),
            std::env::var_os("XDG_STATE_HOME"),
            std::env::var_os("HOME"),
        )
    }
}

/// The state directory when nothing names one: `system` if this user may create files there
/// (`system_writable`), else `$XDG_STATE_HOME/hgcd`, else `$HOME/.local/state/hgcd` (the XDG
/// default), else `system` (whose error then says what to do).
fn default_state_dir(
    system: &Path,
    system_writable: bool,
    xdg_state_home: Option<std::ffi::OsString>,
    home: Option<std::ffi::OsString>,
) -> PathBuf {
    // The XDG spec ignores relative paths.
    let absolute = |v: Option<std::ffi::OsString>| v.map(PathBuf::from).filter(|p| p.is_absolute());
    if system_writable {
        system.to_path_buf()
    } else if let Some(state) = absolute(xdg_state_home) {
        state.join("hgcd")
    } else if let Some(home) = absolute(home) {
        home.join(".local/state/hgcd")
    } else {
        system.to_path_buf()
    }
}

/// Whether this process may create `dir` (when missing) and files in it: the nearest existing
/// directory on its path is writable and searchable for the effective user.
fn may_create_in(dir: &Path) -> bool {
    use std::os::unix::ffi::OsStrExt;
    let Some(existing) = dir.ancestors().find(|a| a.exists()) else {
        return false;
    };
    let Ok(path) = std::ffi::CString::new(existing.as_os_str().as_bytes()) else {
        return false;
    };
    // SAFETY: faccessat only reads the NUL-terminated path, which outlives the call.
    unsafe {
        libc::faccessat(
            libc::AT_FDCWD,
            path.as_ptr(),
            libc::W_OK | libc::X_OK,
            libc::AT_EACCESS,
        ) == 0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_default_state_dir_is_the_system_one_where_writable_else_the_users() {
        let system = Path::new(DEFAULT_STATE_DIR);
        let os = |s: &str| Some(std::ffi::OsString::from(s));
        // root, or user hgcd: /var/lib/hgcd.
        assert_eq!(
            default_state_dir(system, true, os("/x"), os("/home/ann")),
            system
        );
        // Anyone else: their own state directory, XDG first.
        assert_eq!(
            default_state_dir(system, false, os("/x"), os("/home/ann")),
            Path::new("/x/hgcd")
        );
        assert_eq!(
            default_state_dir(system, false, None, os("/home/ann")),
            Path::new("/home/ann/.local/state/hgcd")
        );
        assert_eq!(
            default_state_dir(system, false, os("relative"), os("/home/ann")),
            Path::new("/home/ann/.local/state/hgcd")
        );
        // No home at all: the system directory, whose error says to use --state-dir.
        assert_eq!(default_state_dir(system, false, None, None), system);
        // The nearest existing directory decides whether a missing one may be created.
        let dir = tempfile::tempdir().unwrap();
        assert!(may_create_in(&dir.path().join("a/b")));
    }

    /// `line` without the `#` or `# ` that comments out a setting in the shipped file.
    fn bare(line: &str) -> &str {
        line.strip_prefix('#')
            .map_or(line, |rest| rest.strip_prefix(' ').unwrap_or(rest))
    }

    /// Whether `line`, commented out or not, sets a key (`name = value`).
    fn is_setting(line: &str) -> bool {
        bare(line).split_once(" = ").is_some_and(|(k, _)| {
            !k.is_empty() && k.chars().all(|c| c.is_ascii_lowercase() || c == '_')
        })
    }

    #[test]
    fn shipped_config_file_sets_nothing_and_shows_the_defaults() {
        let text = include_str!("../config/hgcd.toml");
        // The package's conffile: every key commented out, so hgcd runs on the defaults.
        let active: Vec<&str> = text
            .lines()
            .filter(|l| !l.starts_with('#') && is_setting(l))
            .collect();
        assert!(
            active.is_empty(),
            "keys set in config/hgcd.toml: {active:?}"
        );
        let parsed = Config::from_toml_str(text, Path::new("config/hgcd.toml")).unwrap();
        assert_eq!(parsed, Config::default());
        // `#key = value` shows the default: uncommented, they give the defaults again (`# key =
        // value` is an example for a key without one, left commented).
        let shown: Vec<&str> = text
            .lines()
            .map(|l| match l.strip_prefix('#') {
                Some(rest) if !rest.starts_with(' ') && is_setting(rest) => rest,
                _ => l,
            })
            .collect();
        assert!(shown.len() > 40, "too few defaults shown");
        let parsed = Config::from_toml_str(&shown.join("\n"), Path::new("t")).unwrap();
        assert_eq!(parsed, Config::default());
    }

    #[test]
    fn subset_takes_defaults() {
        let c = Config::from_toml_str("[servo]\nwatchdog_ms = 5.0\n", Path::new("t")).unwrap();
        assert_eq!(c.servo.watchdog_ms, 5.0);
        assert_eq!(c.servo.rate_hz, 1000.0);
        assert_eq!(c.sim, SimConfig::default());
    }

    #[test]
    fn unknown_keys_and_bad_values_name_the_key() {
        let err = Config::from_toml_str("[servo]\nwatchdg_ms = 5.0\n", Path::new("t"))
            .unwrap_err()
            .to_string();
        assert!(err.contains("watchdg_ms"), "{err}");
        let err = Config::from_toml_str("[safety]\nmax_force_n = -1.0\n", Path::new("t"))
            .unwrap_err()
            .to_string();
        assert!(err.contains("safety.max_force_n"), "{err}");
        let err = Config::from_toml_str("[servo]\nrate_hz = \"fast\"\n", Path::new("t"))
            .unwrap_err()
            .to_string();
        assert!(err.contains("rate_hz"), "{err}");
        let err = Config::from_toml_str("[device]\nspec = \"usb:1\"\n", Path::new("t"))
            .unwrap_err()
            .to_string();
        assert!(err.contains("usb:1"), "{err}");
    }

    fn parse(text: &str) -> Result<Config, ConfigError> {
        Config::from_toml_str(text, Path::new("t"))
    }

    /// `[section]\nname = value` for a dotted key.
    fn one_key(key: &str, value: &str) -> String {
        let (section, name) = key.split_once('.').unwrap();
        format!("[{section}]\n{name} = {value}\n")
    }

    /// How the shipped file writes a key's value: array, integer or float (absent keys are the
    /// optional ones, shown commented out).
    #[derive(Clone, Copy, PartialEq)]
    enum Shape {
        Float,
        Integer,
        Array,
    }

    fn shape(key: &str) -> Shape {
        let uncommented: Vec<&str> = include_str!("../config/hgcd.toml")
            .lines()
            .map(|line| if is_setting(line) { bare(line) } else { line })
            .collect();
        let shipped: toml::Table = uncommented.join("\n").parse().unwrap();
        let (section, name) = key.split_once('.').unwrap();
        let commented_array = include_str!("../config/hgcd.toml")
            .lines()
            .any(|line| line.starts_with('#') && bare(line).starts_with(&format!("{name} = [")));
        match shipped[section].get(name) {
            Some(toml::Value::Array(_)) => Shape::Array,
            Some(toml::Value::Integer(_)) => Shape::Integer,
            None if commented_array => Shape::Array,
            _ => Shape::Float,
        }
    }

    /// `value` written for `key`: every element of an array key.
    fn written(key: &str, value: &str) -> String {
        match shape(key) {
            Shape::Array => one_key(key, &format!("[{value}, {value}, {value}]")),
            _ => one_key(key, value),
        }
    }

    #[test]
    fn values_from_the_issue_are_refused_with_key_value_and_range_on_one_line() {
        // Each of these was accepted, then panicked the servo thread (watchdog), panicked at
        // start-up (hello timeout 1e308), was silently not applied (hello timeout 1e-9), hung the
        // simulated device (substeps) or turned a safety limit off (max force, stale offset).
        for (key, value, message) in [
            (
                "servo.watchdog_ms",
                "1e308",
                "config key `servo.watchdog_ms`: 1e308 is out of range (1 to 1000 ms)",
            ),
            (
                "app.hello_timeout_ms",
                "1e308",
                "config key `app.hello_timeout_ms`: 1e308 is out of range (10 to 60000 ms)",
            ),
            (
                "app.hello_timeout_ms",
                "1e-9",
                "config key `app.hello_timeout_ms`: 1e-9 is out of range (10 to 60000 ms)",
            ),
            (
                "sim.substep_hz",
                "1e308",
                "config key `sim.substep_hz`: 1e308 is out of range (100 to 1000000 Hz)",
            ),
            (
                "safety.max_force_n",
                "1e308",
                "config key `safety.max_force_n`: 1e308 is out of range (0.1 to 50 N)",
            ),
            (
                "app.stale_offset_ms",
                "1e308",
                "config key `app.stale_offset_ms`: 1e308 is out of range (1 to 1000 ms)",
            ),
        ] {
            let err = parse(&one_key(key, value)).unwrap_err();
            assert!(
                matches!(err, ConfigError::OutOfRange { key: k, .. } if k == key),
                "{err:?}"
            );
            assert_eq!(err.to_string(), message);
        }
    }

    #[test]
    fn nan_and_infinities_are_refused_for_every_numeric_key() {
        for (key, _) in RANGES {
            for value in ["nan", "inf", "-inf"] {
                let err = parse(&written(key, value)).unwrap_err();
                let text = err.to_string();
                assert_eq!(text.lines().count(), 1, "{text}");
                if shape(key) == Shape::Integer {
                    // Not an integer: the TOML layer refuses it, quoting the line.
                    assert!(matches!(err, ConfigError::Parse { .. }), "{err:?}");
                    assert!(text.contains(key.split_once('.').unwrap().1), "{text}");
                } else {
                    assert!(
                        matches!(err, ConfigError::OutOfRange { key: k, .. } if k == *key),
                        "{key} = {value}: {err:?}"
                    );
                    assert!(text.contains(&format!("`{key}`: {value} is out")), "{text}");
                }
            }
        }
    }

    #[test]
    fn every_range_holds_at_its_bounds_and_refuses_just_beyond() {
        for (key, range) in RANGES {
            let integer = shape(key) == Shape::Integer;
            let show = |v: f64| {
                if integer {
                    format!("{v}")
                } else {
                    format!("{v:?}")
                }
            };
            for bound in [range.min, range.max] {
                // A bound may still break a cross-key rule at the other keys' defaults, but it
                // is never out of range.
                if let Err(e) = parse(&written(key, &show(bound))) {
                    assert!(!matches!(e, ConfigError::OutOfRange { .. }), "{key}: {e}");
                }
            }
            let step = |v: f64| {
                if integer {
                    1.0
                } else {
                    (v.abs() * 1e-6).max(1e-9)
                }
            };
            for beyond in [range.min - step(range.min), range.max + step(range.max)] {
                match parse(&written(key, &show(beyond))) {
                    Err(ConfigError::OutOfRange {
                        key: k,
                        value,
                        range: r,
                    }) => {
                        assert_eq!((k, value, r), (*key, beyond, *range));
                    }
                    // An unsigned key cannot even hold -1.
                    Err(ConfigError::Parse { .. }) if integer && beyond < 0.0 => {}
                    other => panic!("{key} = {beyond}: {other:?}"),
                }
            }
        }
    }

    #[test]
    fn the_shipped_file_states_every_range_above_its_key() {
        let text = include_str!("../config/hgcd.toml");
        for (key, range) in RANGES {
            let (section, name) = key.split_once('.').unwrap();
            let body = text
                .split(&format!("[{section}]\n"))
                .nth(1)
                .and_then(|rest| rest.split("\n[").next())
                .unwrap_or_else(|| panic!("no [{section}] in config/hgcd.toml"));
            // The comment block above `name = ...` (or `# name = ...`) and the settings it
            // documents together (`workspace_min_mm` and `workspace_max_mm` share one).
            let mut doc = Vec::new();
            let mut after_setting = false;
            for line in body.lines() {
                if bare(line).starts_with(&format!("{name} = ")) {
                    break;
                }
                if is_setting(line) {
                    after_setting = true;
                } else if line.starts_with('#') {
                    if after_setting {
                        doc.clear();
                        after_setting = false;
                    }
                    doc.push(line);
                }
            }
            let doc = doc.join(" ");
            assert!(
                doc.contains(&format!("Range: {range}")),
                "config/hgcd.toml must say `Range: {range}` above {key}: {doc}"
            );
        }
    }

    fn info(centre_mm: [f64; 3], half_mm: [f64; 3]) -> DeviceInfo {
        DeviceInfo {
            model: "PHANToM-like 3".into(),
            serial: "SN-1".into(),
            workspace_centre: mm(centre_mm),
            workspace_half_extents: mm(half_mm),
            max_force: 3.0,
            rate_hz: 1000.0,
            lockstep: false,
        }
    }

    #[test]
    fn a_device_workspace_stands_in_for_the_keys_the_file_does_not_give() {
        let config = Config::default();
        assert_eq!(config.for_device(None), config);
        // A workspace 150 mm from the origin: the safe box is the device's, the grid is centred
        // in it, and the paper's 40 mm cube fits with a quarter of each half-extent to spare.
        let far = info([0.0, 150.0, 60.0], [80.0, 60.0, 60.0]);
        let c = config.for_device(Some(&far));
        assert_eq!(c.device.workspace_min_mm, [-80.0, 90.0, 0.0]);
        assert_eq!(c.device.workspace_max_mm, [80.0, 210.0, 120.0]);
        assert_eq!(c.calibration.centre_mm, [0.0, 150.0, 60.0]);
        assert_eq!(c.calibration.spacing_mm, 40.0);
        // A small workspace: the cube shrinks to 0.75 × 30 mm per half-size.
        let small = info([10.0, 0.0, 0.0], [50.0, 30.0, 40.0]);
        assert_eq!(config.for_device(Some(&small)).calibration.spacing_mm, 22.5);
        let mut two = config.clone();
        two.calibration.half_size = 2;
        assert_eq!(two.for_device(Some(&small)).calibration.spacing_mm, 11.25);
        // The force limit is the smaller of the config's and the device's (3 N here).
        assert_eq!(c.safety.max_force_n, 3.0);
        let mut strong = far.clone();
        strong.max_force = 20.0;
        assert_eq!(config.for_device(Some(&strong)).safety.max_force_n, 8.0);
        // Everything else is the config's.
        let mut rest = c.clone();
        rest.device = config.device.clone();
        rest.calibration.centre_mm = config.calibration.centre_mm;
        rest.safety = config.safety.clone();
        assert_eq!(rest, config);
    }

    #[test]
    fn keys_the_file_gives_win_over_the_device() {
        let given = parse(
            "[device]\nworkspace_max_mm = [70.0, 70.0, 70.0]\n\
             [calibration]\ncentre_mm = [0.0, 0.0, 0.0]\nspacing_mm = 30.0\n",
        )
        .unwrap();
        assert_eq!(
            given.given,
            GivenKeys {
                workspace: true,
                centre: true,
                cube: true
            }
        );
        let mut far = info([0.0, 150.0, 60.0], [80.0, 60.0, 60.0]);
        far.max_force = given.safety.max_force_n;
        assert_eq!(given.for_device(Some(&far)), given);
        // The cube's size is given by either of its keys.
        let n = parse("[calibration]\nhalf_size = 2\n").unwrap();
        let c = n.for_device(Some(&info([0.0; 3], [30.0; 3])));
        assert_eq!(c.calibration.spacing_mm, 40.0);
        assert_eq!(c.device.workspace_max_mm, [30.0; 3]);
        // The shipped file leaves them to the device.
        let shipped = parse(include_str!("../config/hgcd.toml")).unwrap();
        assert_eq!(shipped.given, GivenKeys::default());
    }

    #[test]
    fn a_sim_serial_the_device_info_report_cannot_carry_is_refused() {
        let err = parse("[sim]\nserial = \"0123456789ABC\"\n")
            .unwrap_err()
            .to_string();
        assert!(
            err.starts_with("config key `sim.serial`: \"0123456789ABC\" is not a serial number")
                && err.contains("at most 12 bytes"),
            "{err}"
        );
        assert!(parse("[sim]\nserial = \"a\\tb\"\n").is_err());
        assert_eq!(
            parse("[sim]\nserial = \"SN-0001\"\n").unwrap().sim.serial,
            "SN-0001"
        );
    }

    #[test]
    fn cross_key_rules_name_the_key_and_the_rule() {
        let refused = |text: &str, key: &str, says: &str| {
            let err = parse(text).unwrap_err();
            let line = err.to_string();
            assert!(
                matches!(&err, ConfigError::Invalid { key: k, .. } if k == key),
                "{err:?}"
            );
            assert!(line.contains(says), "{line}");
            assert_eq!(line.lines().count(), 1, "{line}");
        };
        refused(
            "[sim]\nobstacle_min_mm = [30.0, 30.0, 30.0]\n",
            "sim.obstacle_max_mm",
            "an obstacle needs both corners",
        );
        refused(
            "[sim]\nobstacle_min_mm = [30.0, 30.0, 30.0]\nobstacle_max_mm = [80.0, 20.0, 80.0]\n",
            "sim.obstacle_max_mm",
            "on the y axis",
        );
        // At 100 Hz two report periods are 20 ms.
        refused(
            "[servo]\nrate_hz = 100.0\nwatchdog_ms = 15.0\n",
            "servo.watchdog_ms",
            "15 ms is shorter than two report periods (20 ms at servo.rate_hz = 100)",
        );
        refused(
            "[servo]\nrate_hz = 100.0\nwatchdog_ms = 20.0\n[sim]\ndevice_watchdog_ms = 19.0\n",
            "sim.device_watchdog_ms",
            "two report periods",
        );
        refused(
            "[servo]\nrate_hz = 100.0\nwatchdog_ms = 20.0\n[app]\nstale_offset_ms = 10.0\n",
            "app.stale_offset_ms",
            "two report periods",
        );
        refused(
            "[servo]\nrate_hz = 5000.0\n[sim]\nsubstep_hz = 2000.0\n",
            "sim.substep_hz",
            "below servo.rate_hz (5000 Hz)",
        );
        refused(
            "[servo]\nrate_hz = 100.0\nwatchdog_ms = 20.0\n[calibration]\nrise_time_ms = 50.0\n",
            "calibration.rise_time_ms",
            "ten report periods (100 ms",
        );
        refused(
            "[device]\nworkspace_min_mm = [0.0, 0.0, 0.0]\nworkspace_max_mm = [10.0, -10.0, 10.0]\n",
            "device.workspace_max_mm",
            "-10 is not above device.workspace_min_mm's 0 on the y axis",
        );
        refused(
            "[sim]\nworkspace_min_mm = [0.0, 5.0, 0.0]\nworkspace_max_mm = [10.0, 5.0, 10.0]\n",
            "sim.workspace_max_mm",
            "on the y axis",
        );
        refused(
            "[sim]\ngravity_direction = [0.0, 0.0, 0.0]\n",
            "sim.gravity_direction",
            "must not be the zero vector",
        );
        refused(
            "[validation]\ndither_s = 0.1\n",
            "validation.dither_s",
            "under five periods",
        );
        // The same rules at a rate where they are met.
        parse(
            "[servo]\nrate_hz = 100.0\nwatchdog_ms = 20.0\n[sim]\ndevice_watchdog_ms = 20.0\n\
             [app]\nstale_offset_ms = 20.0\n[calibration]\nrise_time_ms = 100.0\n",
        )
        .unwrap();
        // A stale offset needs a ramp to zero of at least a millisecond, never an instant one.
        assert!(matches!(
            parse("[app]\nstale_ramp_ms = 0.0\n").unwrap_err(),
            ConfigError::OutOfRange {
                key: "app.stale_ramp_ms",
                ..
            }
        ));
    }

    #[test]
    fn a_config_built_in_code_is_checked_by_validate() {
        let mut config = Config::default();
        config.validate().unwrap();
        config.servo.watchdog_ms = f64::INFINITY;
        assert!(matches!(
            config.validate().unwrap_err(),
            ConfigError::OutOfRange {
                key: "servo.watchdog_ms",
                ..
            }
        ));
        let mut config = Config::default();
        config.calibration.n_m = 0;
        assert!(matches!(
            config.validate().unwrap_err(),
            ConfigError::OutOfRange {
                key: "calibration.n_m",
                ..
            }
        ));
    }

    #[test]
    fn accessors_convert_file_units_to_si() {
        let c = Config::default();
        let close = |a: f64, b: f64| (a - b).abs() <= 1e-12 * b.abs().max(1.0);
        assert!(close(c.servo.period(), 1e-3));
        assert!(close(c.servo.watchdog(), 0.010));
        assert!(close(c.estimate.noise_bound(), 1e-5));
        assert!(close(c.sim.encoder_resolution(), 5e-6));
        assert!(close(c.sim.noise(), 2e-6));
        assert!(close(c.sim.device_watchdog(), 0.050));
        assert_eq!(
            c.sim.workspace(),
            (Vector3::repeat(-0.08), Vector3::repeat(0.08))
        );
        assert_eq!(
            c.device.workspace(),
            (Vector3::repeat(-0.07), Vector3::repeat(0.07))
        );
        assert_eq!(c.sim.start_position(), Vector3::zeros());
        let cal = &c.calibration;
        assert!(close(cal.spacing(), 0.040));
        assert_eq!(cal.centre(), Vector3::zeros());
        assert!(close(cal.k_init(), 500.0));
        assert!(close(cal.eps_init(), 1e-4));
        assert!(close(cal.eps_m(), 1e-4));
        assert!(close(cal.rise_time(), 0.100));
        assert!(close(cal.move_time(), 0.400));
        assert!(close(c.app.stale_offset(), 0.050));
        assert!(close(c.app.stale_ramp(), 0.050));
        assert_eq!(c.app.hello_timeout(), Duration::from_secs(5));
        // Both ends of the accepted hello timeout make a real timeout: 1e-9 ms rounded to a zero
        // Duration, which the socket layer refuses, so no timeout applied at all.
        for ms in ["10.0", "60000.0"] {
            let c = parse(&one_key("app.hello_timeout_ms", ms)).unwrap();
            let t = c.app.hello_timeout();
            assert!(
                t >= Duration::from_millis(10) && t <= Duration::from_secs(60),
                "{t:?}"
            );
        }
    }

    #[test]
    fn device_specs_parse_and_name_files() {
        let hid: DeviceSpec = "hid:1234:abcd:SN 7".parse().unwrap();
        assert_eq!(
            hid,
            DeviceSpec::Hid {
                vid: 0x1234,
                pid: 0xabcd,
                serial: Some("SN 7".into())
            }
        );
        assert_eq!(hid.device_id(), "hid-1234-abcd-SN_7");
        assert_eq!(
            "sim:point-mass".parse::<DeviceSpec>().unwrap().device_id(),
            "sim-point-mass"
        );
        assert!("sim:nope".parse::<DeviceSpec>().is_err());
        assert!("hid:12345:1".parse::<DeviceSpec>().is_err());
        assert_eq!(
            "socket:/tmp/dev.sock"
                .parse::<DeviceSpec>()
                .unwrap()
                .to_string(),
            "socket:/tmp/dev.sock"
        );
    }
}
