//! Typed configuration (`config/hgcd.toml` documents every key). Any subset of keys may be given;
//! the rest take their defaults. Unknown keys and invalid values are rejected with the key's name.
//! Units in the file are the ones users speak (mm, N/mm, ms); the accessors on each section are
//! the one place they are converted to SI (m, s, N/m).

use std::fmt;
use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::time::Duration;

use nalgebra::Vector3;
use serde::Deserialize;
use thiserror::Error;

use crate::control::compensation::{CompensationMode, OutsideGrid};
use crate::estimate::FoawVariant;

/// Default configuration file of an installed daemon.
pub const DEFAULT_CONFIG_PATH: &str = "/etc/hgcd/hgcd.toml";
/// Default directory for calibration grids.
pub const DEFAULT_STATE_DIR: &str = "/var/lib/hgcd";
/// Default application socket.
pub const DEFAULT_SOCKET: &str = "/run/hgcd/hgcd.sock";

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
    #[error("device spec `{spec}`: {message}")]
    DeviceSpec { spec: String, message: String },
}

fn invalid(key: &str, message: impl Into<String>) -> ConfigError {
    ConfigError::Invalid {
        key: key.to_string(),
        message: message.into(),
    }
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
pub const SIM_MODELS: &[&str] = &["point-mass"];

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

impl DeviceSpec {
    /// Stable identity used to name the device's calibration file (`<state_dir>/<id>.toml`).
    pub fn device_id(&self) -> String {
        let clean = |s: &str| -> String {
            s.chars()
                .map(|c| {
                    if c.is_ascii_alphanumeric() || c == '-' {
                        c
                    } else {
                        '_'
                    }
                })
                .collect()
        };
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

/// The whole configuration.
#[derive(Clone, Debug, Default, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct Config {
    pub device: DeviceConfig,
    pub servo: ServoConfig,
    pub safety: SafetyConfig,
    pub estimate: EstimateConfig,
    pub sim: SimConfig,
    pub calibration: CalibrationConfig,
    pub compensation: CompensationConfig,
    pub app: AppConfig,
    pub paths: PathsConfig,
}

#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct DeviceConfig {
    /// Device spec used when the command line gives none.
    pub spec: String,
    /// Box the handle may safely be driven in, mm, in the device frame (smallest corner).
    pub workspace_min_mm: [f64; 3],
    /// Largest corner of that box, mm.
    pub workspace_max_mm: [f64; 3],
}

impl Default for DeviceConfig {
    fn default() -> Self {
        Self {
            spec: "sim:point-mass".into(),
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
    /// Mass field from an `hgcd-grid/1` file (its gravity_direction and g then apply); empty: uniform.
    pub mass_grid: Option<PathBuf>,
    /// Uniform apparent mass when no grid is given, kg.
    pub mass_kg: f64,
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
    /// Viscous friction, N·s/m.
    pub damping_n_s_per_m: f64,
    /// Probe mass attached to the end effector, kg (the paper's validation uses 30 g).
    pub probe_mass_kg: f64,
    /// Integration rate, Hz (at least 10 kHz).
    pub substep_hz: f64,
    /// The device zeroes force when no output report arrives for this long, ms.
    pub device_watchdog_ms: f64,
    /// Fault injection: the device stops reporting after this much device time, s.
    pub stop_reporting_after_s: Option<f64>,
}

impl Default for SimConfig {
    fn default() -> Self {
        Self {
            seed: 1,
            mass_grid: None,
            mass_kg: 0.12,
            g: 9.81,
            gravity_direction: [0.0, 0.0, 1.0],
            workspace_min_mm: [-80.0; 3],
            workspace_max_mm: [80.0; 3],
            start_position_mm: [0.0; 3],
            max_force_n: 10.0,
            encoder_resolution_mm: 0.005,
            noise_mm: 0.002,
            damping_n_s_per_m: 0.0,
            probe_mass_kg: 0.0,
            substep_hz: 10_000.0,
            device_watchdog_ms: 50.0,
            stop_reporting_after_s: None,
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
        }
    }
}

#[derive(Clone, Debug, Default, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct CompensationConfig {
    /// "scalar" (paper: M(X) g v_G) or "vector" (interpolated calibrated force vectors).
    pub mode: CompensationMode,
    /// Outside the grid: "hold-nearest" (nearest cell's face values) or "zero".
    pub outside_grid: OutsideGrid,
    /// Run without compensation when the grid is corrupt or made for another device (a missing
    /// grid always runs uncompensated, so the device can be calibrated through the daemon).
    pub allow_uncompensated: bool,
}

#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct AppConfig {
    /// Application socket; default $RUNTIME_DIRECTORY/hgcd.sock, else /run/hgcd/hgcd.sock.
    pub socket: Option<PathBuf>,
    /// Permissions of the socket file (octal, as a string).
    pub socket_mode: String,
    /// A force offset not refreshed for this long ramps to zero, ms.
    pub stale_offset_ms: f64,
    /// Duration of that ramp from the full offset to zero, ms.
    pub stale_ramp_ms: f64,
    /// Most clients connected at once; more are refused.
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
    /// Where calibration grids live; systemd's STATE_DIRECTORY overrides the default.
    pub state_dir: Option<PathBuf>,
}

#[allow(clippy::derivable_impls)]
impl Default for PathsConfig {
    fn default() -> Self {
        Self { state_dir: None }
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

fn positive(key: &str, v: f64) -> Result<(), ConfigError> {
    if v.is_finite() && v > 0.0 {
        Ok(())
    } else {
        Err(invalid(key, format!("must be a positive number, got {v}")))
    }
}

fn non_negative(key: &str, v: f64) -> Result<(), ConfigError> {
    if v.is_finite() && v >= 0.0 {
        Ok(())
    } else {
        Err(invalid(key, format!("must be zero or positive, got {v}")))
    }
}

fn ordered_box(key: &str, lo: [f64; 3], hi: [f64; 3]) -> Result<(), ConfigError> {
    if (0..3).all(|a| lo[a].is_finite() && hi[a].is_finite() && lo[a] < hi[a]) {
        Ok(())
    } else {
        Err(invalid(
            key,
            "each minimum must be finite and below its maximum",
        ))
    }
}

impl Config {
    /// Parse and validate TOML text; `origin` names the source in messages.
    pub fn from_toml_str(text: &str, origin: &Path) -> Result<Self, ConfigError> {
        let config: Config = toml::from_str(text).map_err(|e| ConfigError::Parse {
            path: origin.to_path_buf(),
            message: e.to_string().trim().replace('\n', " "),
        })?;
        config.validate()?;
        Ok(config)
    }

    /// Load a config file.
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|error| ConfigError::Read {
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
        Ok(config)
    }

    /// Check every value; the error names the offending key.
    pub fn validate(&self) -> Result<(), ConfigError> {
        self.device_spec()?;
        ordered_box(
            "device.workspace_min_mm/workspace_max_mm",
            self.device.workspace_min_mm,
            self.device.workspace_max_mm,
        )?;
        let s = &self.servo;
        if !(s.rate_hz.is_finite() && (10.0..=20_000.0).contains(&s.rate_hz)) {
            return Err(invalid("servo.rate_hz", "must be between 10 and 20000 Hz"));
        }
        positive("servo.watchdog_ms", s.watchdog_ms)?;
        if s.realtime_priority > 99 {
            return Err(invalid(
                "servo.realtime_priority",
                "must be 0 (normal) or 1–99",
            ));
        }
        if s.cpu < -1 || s.cpu >= libc::CPU_SETSIZE {
            return Err(invalid(
                "servo.cpu",
                format!("must be a CPU index below {} or -1", libc::CPU_SETSIZE),
            ));
        }
        positive("safety.max_force_n", self.safety.max_force_n)?;
        positive(
            "safety.max_force_rate_n_per_s",
            self.safety.max_force_rate_n_per_s,
        )?;
        positive("estimate.noise_bound_mm", self.estimate.noise_bound_mm)?;
        if !(1..=crate::estimate::foaw::MAX_WINDOW).contains(&self.estimate.max_window) {
            return Err(invalid(
                "estimate.max_window",
                format!("must be 1–{}", crate::estimate::foaw::MAX_WINDOW),
            ));
        }
        let sim = &self.sim;
        positive("sim.mass_kg", sim.mass_kg)?;
        positive("sim.g", sim.g)?;
        let gd = Vector3::from(sim.gravity_direction);
        if !(gd.norm().is_finite() && gd.norm() > 1e-9) {
            return Err(invalid(
                "sim.gravity_direction",
                "must be a non-zero vector",
            ));
        }
        ordered_box(
            "sim.workspace_min_mm/workspace_max_mm",
            sim.workspace_min_mm,
            sim.workspace_max_mm,
        )?;
        positive("sim.max_force_n", sim.max_force_n)?;
        non_negative("sim.encoder_resolution_mm", sim.encoder_resolution_mm)?;
        non_negative("sim.noise_mm", sim.noise_mm)?;
        non_negative("sim.damping_n_s_per_m", sim.damping_n_s_per_m)?;
        non_negative("sim.probe_mass_kg", sim.probe_mass_kg)?;
        if !(sim.substep_hz.is_finite() && sim.substep_hz >= 10_000.0) {
            return Err(invalid("sim.substep_hz", "must be at least 10000 Hz"));
        }
        positive("sim.device_watchdog_ms", sim.device_watchdog_ms)?;
        if let Some(t) = sim.stop_reporting_after_s {
            non_negative("sim.stop_reporting_after_s", t)?;
        }
        let c = &self.calibration;
        positive("calibration.spacing_mm", c.spacing_mm)?;
        if c.half_size == 0 || c.half_size > 10 {
            return Err(invalid("calibration.half_size", "must be 1–10"));
        }
        if !c.centre_mm.iter().all(|v| v.is_finite()) {
            return Err(invalid("calibration.centre_mm", "must be finite"));
        }
        positive("calibration.k_init_n_per_mm", c.k_init_n_per_mm)?;
        non_negative(
            "calibration.init_damping_n_s_per_m",
            c.init_damping_n_s_per_m,
        )?;
        if c.n_init == 0 {
            return Err(invalid("calibration.n_init", "must be at least 1"));
        }
        if c.n_m == 0 {
            return Err(invalid("calibration.n_m", "must be at least 1"));
        }
        positive("calibration.eps_init_mm", c.eps_init_mm)?;
        positive("calibration.eps_m_mm", c.eps_m_mm)?;
        positive("calibration.g", c.g)?;
        positive("calibration.rise_time_ms", c.rise_time_ms)?;
        positive("calibration.damping_ratio", c.damping_ratio)?;
        positive("calibration.move_time_ms", c.move_time_ms)?;
        positive("calibration.vertex_timeout_s", c.vertex_timeout_s)?;
        if c.max_iterations < 2 {
            return Err(invalid(
                "calibration.max_iterations",
                "must be at least 2 (a vertex ends at its second steady state near the vertex)",
            ));
        }
        let a = &self.app;
        self.socket_mode()?;
        positive("app.stale_offset_ms", a.stale_offset_ms)?;
        positive("app.stale_ramp_ms", a.stale_ramp_ms)?;
        positive("app.hello_timeout_ms", a.hello_timeout_ms)?;
        if a.max_clients == 0 || a.max_clients > 1024 {
            return Err(invalid("app.max_clients", "must be 1–1024"));
        }
        Ok(())
    }

    /// The configured device spec.
    pub fn device_spec(&self) -> Result<DeviceSpec, ConfigError> {
        self.device.spec.parse()
    }

    /// Nominal servo period, s.
    pub fn servo_period(&self) -> f64 {
        self.servo.period()
    }

    /// The socket file's permission bits.
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

    /// Application socket: config, else `$RUNTIME_DIRECTORY/hgcd.sock` (systemd), else
    /// /run/hgcd/hgcd.sock.
    pub fn socket_path(&self) -> PathBuf {
        if let Some(path) = &self.app.socket {
            return path.clone();
        }
        if let Ok(dirs) = std::env::var("RUNTIME_DIRECTORY") {
            if let Some(first) = dirs.split(':').find(|s| !s.is_empty()) {
                return PathBuf::from(first).join("hgcd.sock");
            }
        }
        PathBuf::from(DEFAULT_SOCKET)
    }

    /// Calibration state directory: config, else `$STATE_DIRECTORY` (systemd), else /var/lib/hgcd.
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
        PathBuf::from(DEFAULT_STATE_DIR)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shipped_config_file_equals_the_defaults() {
        let text = include_str!("../config/hgcd.toml");
        let parsed = Config::from_toml_str(text, Path::new("config/hgcd.toml")).unwrap();
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
