//! Device profiles: what a device speaks on the wire and, for a joint-space device, the
//! kinematics the host does for it (`docs/devices.md`). A profile is a TOML file: the built-in
//! ones ship in `config/profiles/` (compiled in), a user adds their own as `NAME.toml` in a
//! `profiles/` directory beside the config file, and `device.profile` or `--profile` picks one
//! by name or path. Without a choice, a HID device whose USB IDs a profile claims gets that
//! profile, `sim:woodenhaptics` gets `woodenhaptics_v2015`, and anything else the default,
//! [`CARTESIAN_V1`].
//!
//! [`Codec`] is the profile's place in the servo loop: between the transport's raw report bytes
//! and the loop's Cartesian position and force in SI units. It allocates nothing.

#[cfg(test)]
mod fuzz;
pub mod kinematics;
pub mod woodenhaptics;

use std::path::{Path, PathBuf};

use nalgebra::Vector3;
use serde::Deserialize;
use thiserror::Error;

use crate::arm::{Arm, ArmTable, GeometryTolerances};
use crate::config::{Config, DeviceSpec};
use crate::protocol::{
    DeviceInfo, InputReport, OutputReport, ProtocolError, Status, OUTPUT_REPORT_LEN,
};
pub use kinematics::ArmModel;
use woodenhaptics::{CurrentReport, EncoderReport, REPORT_LEN};

/// Name of the default profile: hgcd HID report protocol v1.
pub const CARTESIAN_V1: &str = "cartesian-v1";
/// The profile `sim:woodenhaptics` uses unless a WoodenHaptics-protocol profile is configured.
pub const SIM_PROFILE: &str = "woodenhaptics_v2015";

/// Longest profile name, bytes.
pub const NAME_LEN: usize = 32;

/// The profiles that ship with hgcd (`config/profiles/`), in the order they claim USB IDs.
const BUILT_IN: &[(&str, &str)] = &[
    (
        CARTESIAN_V1,
        include_str!("../../config/profiles/cartesian-v1.toml"),
    ),
    (
        "woodenhaptics_v2015",
        include_str!("../../config/profiles/woodenhaptics_v2015.toml"),
    ),
    (
        "polhem_v1",
        include_str!("../../config/profiles/polhem_v1.toml"),
    ),
    (
        PHANTOM_PROFILE,
        include_str!("../../config/profiles/phantom_1_5.toml"),
    ),
    (
        DELTA_PROFILE,
        include_str!("../../config/profiles/falcon_delta.toml"),
    ),
];

/// The profiles `sim:phantom` and `sim:delta` use unless a Cartesian profile is configured.
pub const PHANTOM_PROFILE: &str = "phantom_1_5";
pub const DELTA_PROFILE: &str = "falcon_delta";

/// Why a profile cannot be used.
#[derive(Debug, Error)]
pub enum ProfileError {
    #[error(
        "no device profile `{name}` (built in: {}; or put {name}.toml in {})",
        built_in_names().join(", "),
        dir.display()
    )]
    Unknown { name: String, dir: PathBuf },
    #[error("cannot read device profile {path}: {source}")]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("device profile {origin}: {message}")]
    Invalid { origin: String, message: String },
    #[error("device profile {origin}: `{key}` = {value} is out of range ({min} to {max} {unit})")]
    OutOfRange {
        origin: String,
        key: &'static str,
        value: f64,
        min: f64,
        max: f64,
        unit: &'static str,
    },
}

fn built_in_names() -> Vec<&'static str> {
    BUILT_IN.iter().map(|(n, _)| *n).collect()
}

/// The wire protocol a profile speaks.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize)]
pub enum Wire {
    /// hgcd HID report protocol v1 (`docs/hid-protocol.md`), with its device-info report.
    #[serde(rename = "cartesian-v1")]
    CartesianV1,
    /// The WoodenHaptics / Polhem protocol ([`woodenhaptics`]): no report IDs, no device info.
    #[serde(rename = "woodenhaptics")]
    WoodenHaptics,
}

impl Wire {
    /// Whether `bytes` is an input report of this protocol (a transport keeps the newest such
    /// report of a burst).
    pub fn input_valid(self, bytes: &[u8]) -> bool {
        match self {
            Wire::CartesianV1 => InputReport::decode(bytes).is_ok(),
            Wire::WoodenHaptics => EncoderReport::decode(bytes).is_ok(),
        }
    }

    /// Whether devices of this protocol answer the device-info feature report.
    pub fn has_device_info(self) -> bool {
        self == Wire::CartesianV1
    }

    /// Whether reports carry a report ID as their first byte (else hidapi is handed a 0 first).
    pub fn numbered_reports(self) -> bool {
        self == Wire::CartesianV1
    }
}

/// Every numeric key of a profile and its range (`docs/devices.md` §3), checked at load; array
/// keys apply it to each element.
pub const RANGES: &[(&str, f64, f64, &str)] = &[
    ("max_force_n", 0.1, 50.0, "N"),
    ("kinematics.lengths_m", 0.0, 1.0, "m"),
    ("kinematics.capstan_diameters_m", 0.001, 0.2, "m"),
    ("kinematics.drum_diameters_m", 0.005, 1.0, "m"),
    ("kinematics.counts_per_rev", 4.0, 1e7, "counts"),
    ("kinematics.torque_constants_nm_per_a", 0.001, 5.0, "N m/A"),
    ("kinematics.max_current_a", 0.01, 30.0, "A"),
    ("kinematics.workspace_origin_m", -1.0, 1.0, "m"),
    ("kinematics.workspace_radius_m", 0.005, 0.5, "m"),
    ("bodies.masses_kg", 0.0, 10.0, "kg"),
    ("bodies.centres_of_mass_m", -1.0, 1.0, "m"),
    ("geometry_tolerances.origin_m", 0.0, 0.01, "m"),
    ("geometry_tolerances.length_share", 0.0, 0.05, ""),
    ("geometry_tolerances.pivot_radius_m", 0.0, 0.005, "m"),
];

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ProfileFile {
    name: String,
    description: String,
    protocol: Wire,
    #[serde(default)]
    usb_ids: Vec<String>,
    max_force_n: Option<f64>,
    kinematics: Option<KinematicsFile>,
    bodies: Option<BodiesFile>,
    arm: Option<ArmTable>,
    geometry_tolerances: Option<TolerancesFile>,
}

/// `[geometry_tolerances]`: how far a unit may sit from the profile's geometry; a key left out
/// keeps [`GeometryTolerances::DEFAULT`]'s.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct TolerancesFile {
    origin_m: Option<f64>,
    length_share: Option<f64>,
    pivot_radius_m: Option<f64>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct KinematicsFile {
    #[serde(deserialize_with = "crate::arm::exact")]
    lengths_m: [f64; 3],
    #[serde(deserialize_with = "crate::arm::exact")]
    capstan_diameters_m: [f64; 3],
    #[serde(deserialize_with = "crate::arm::exact")]
    drum_diameters_m: [f64; 3],
    #[serde(deserialize_with = "crate::arm::exact")]
    motor_and_body_aligned: [bool; 3],
    #[serde(deserialize_with = "crate::arm::exact")]
    counts_per_rev: [f64; 3],
    #[serde(deserialize_with = "crate::arm::exact")]
    torque_constants_nm_per_a: [f64; 3],
    max_current_a: f64,
    #[serde(deserialize_with = "crate::arm::exact")]
    workspace_origin_m: [f64; 3],
    workspace_radius_m: f64,
    #[serde(deserialize_with = "crate::arm::exact")]
    home_counts: [i16; 3],
}

#[derive(Clone, Copy, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct BodiesFile {
    /// Masses of the upper arm and the forearm, kg.
    #[serde(deserialize_with = "crate::arm::exact")]
    pub masses_kg: [f64; 2],
    /// Distance of each one's centre of mass from its joint, m.
    #[serde(deserialize_with = "crate::arm::exact")]
    pub centres_of_mass_m: [f64; 2],
}

/// A device profile, checked.
#[derive(Clone, Debug, PartialEq)]
pub struct Profile {
    pub name: String,
    pub description: String,
    pub wire: Wire,
    /// USB (vendor, product) IDs the profile claims.
    pub usb_ids: Vec<(u16, u16)>,
    /// For a joint-space device: its largest force, N.
    pub max_force: Option<f64>,
    arm: Option<ArmModel>,
    /// The published masses of the arm's bodies (a simulated device is built with them).
    pub bodies: Option<BodiesFile>,
    /// The arm the gravity model knows: the `[arm]` table, or a joint-space arm's kinematics.
    gravity_arm: Option<Arm>,
    /// How far a unit may sit from the arm's geometry (`[geometry_tolerances]`).
    pub geometry_tolerances: GeometryTolerances,
}

impl Profile {
    /// Parse and check the TOML text of a profile; `origin` names it in messages.
    ///
    /// # Errors
    /// [`ProfileError::Invalid`] for TOML, a missing or unknown key, a protocol without the
    /// tables it needs; [`ProfileError::OutOfRange`] for a number outside [`RANGES`].
    pub fn parse(text: &str, origin: &str) -> Result<Self, ProfileError> {
        let invalid = |message: String| ProfileError::Invalid {
            origin: origin.to_string(),
            message,
        };
        let file: ProfileFile =
            toml::from_str(text).map_err(|e| invalid(crate::config::toml_error(text, &e)))?;
        let check = |key: &'static str, values: &[f64]| {
            let &(_, min, max, unit) = RANGES.iter().find(|r| r.0 == key).expect("a ranged key");
            match values.iter().find(|v| !(min..=max).contains(*v)) {
                Some(&value) => Err(ProfileError::OutOfRange {
                    origin: origin.to_string(),
                    key,
                    value,
                    min,
                    max,
                    unit,
                }),
                None => Ok(()),
            }
        };
        let usb_ids = file
            .usb_ids
            .iter()
            .map(|id| {
                let (v, p) = id.split_once(':').unwrap_or((id, ""));
                let hex = |s: &str| u16::from_str_radix(s, 16).ok();
                hex(v).zip(hex(p)).ok_or_else(|| {
                    invalid(format!(
                        "usb_ids: `{id}` is not VID:PID in hex (e.g. 1234:0006)"
                    ))
                })
            })
            .collect::<Result<Vec<_>, _>>()?;
        if let Some(f) = file.max_force_n {
            check("max_force_n", &[f])?;
        }
        let arm = match (file.protocol, file.kinematics) {
            (Wire::CartesianV1, Some(_)) => {
                return Err(invalid(
                    "protocol \"cartesian-v1\" takes no [kinematics] table".into(),
                ))
            }
            (Wire::CartesianV1, None) => None,
            (Wire::WoodenHaptics, None) => {
                return Err(invalid(
                    "protocol \"woodenhaptics\" needs a [kinematics] table".into(),
                ))
            }
            (Wire::WoodenHaptics, Some(k)) => {
                check("kinematics.lengths_m", &k.lengths_m)?;
                check("kinematics.capstan_diameters_m", &k.capstan_diameters_m)?;
                check("kinematics.drum_diameters_m", &k.drum_diameters_m)?;
                check("kinematics.counts_per_rev", &k.counts_per_rev)?;
                if let Some(c) = k.counts_per_rev.iter().find(|c| c.fract() != 0.0) {
                    return Err(invalid(format!(
                        "kinematics.counts_per_rev: {c} is not a whole number of counts"
                    )));
                }
                check(
                    "kinematics.torque_constants_nm_per_a",
                    &k.torque_constants_nm_per_a,
                )?;
                check("kinematics.max_current_a", &[k.max_current_a])?;
                check("kinematics.workspace_origin_m", &k.workspace_origin_m)?;
                check("kinematics.workspace_radius_m", &[k.workspace_radius_m])?;
                let arm = ArmModel {
                    lengths: k.lengths_m.into(),
                    capstans: k.capstan_diameters_m.into(),
                    drums: k.drum_diameters_m.into(),
                    directions: k
                        .motor_and_body_aligned
                        .map(|aligned| if aligned { -1.0 } else { 1.0 })
                        .into(),
                    counts_per_rev: k.counts_per_rev.into(),
                    torque_constants: k.torque_constants_nm_per_a.into(),
                    max_current: k.max_current_a,
                    origin: k.workspace_origin_m.into(),
                    workspace_radius: k.workspace_radius_m,
                    home_counts: k.home_counts,
                };
                if arm.joints_at(&Vector3::zeros()).is_none() {
                    return Err(invalid(
                        "the arm cannot reach kinematics.workspace_origin_m".into(),
                    ));
                }
                Some(arm)
            }
        };
        if arm.is_some() == file.max_force_n.is_none() {
            return Err(invalid(
                "max_force_n is given for, and only for, a joint-space profile".into(),
            ));
        }
        if arm.is_none() && file.bodies.is_some() {
            return Err(invalid(
                "protocol \"cartesian-v1\" takes no [bodies] table".into(),
            ));
        }
        if let Some(b) = &file.bodies {
            check("bodies.masses_kg", &b.masses_kg)?;
            check("bodies.centres_of_mass_m", &b.centres_of_mass_m)?;
        }
        let gravity_arm = match (&file.arm, &arm) {
            (Some(table), _) => Some(
                table
                    .arm()
                    .map_err(|message| invalid(format!("[arm]: {message}")))?,
            ),
            (None, Some(joint_space)) => Some(joint_space.gravity_arm()),
            (None, None) => None,
        };
        let mut geometry_tolerances = GeometryTolerances::DEFAULT;
        if let Some(t) = &file.geometry_tolerances {
            if gravity_arm.is_none() {
                return Err(invalid(
                    "[geometry_tolerances] without an arm: only an arm's geometry has them".into(),
                ));
            }
            let d = GeometryTolerances::DEFAULT;
            geometry_tolerances = GeometryTolerances {
                origin: t.origin_m.unwrap_or(d.origin),
                length: t.length_share.unwrap_or(d.length),
                radius: t.pivot_radius_m.unwrap_or(d.radius),
            };
            let g = &geometry_tolerances;
            check("geometry_tolerances.origin_m", &[g.origin])?;
            check("geometry_tolerances.length_share", &[g.length])?;
            check("geometry_tolerances.pivot_radius_m", &[g.radius])?;
        }
        let name_ok = |c: char| c.is_ascii_alphanumeric() || c == '-' || c == '_';
        if !(1..=NAME_LEN).contains(&file.name.len()) || !file.name.chars().all(name_ok) {
            return Err(invalid(format!(
                "name must be 1 to {NAME_LEN} ASCII letters, digits, `-` or `_` (it names the \
                 device's grid)"
            )));
        }
        Ok(Self {
            name: file.name,
            description: file.description,
            wire: file.protocol,
            usb_ids,
            max_force: file.max_force_n,
            arm,
            bodies: file.bodies,
            gravity_arm,
            geometry_tolerances,
        })
    }

    /// The built-in profile `name`, if there is one.
    pub fn built_in(name: &str) -> Option<Self> {
        BUILT_IN.iter().find(|(n, _)| *n == name).map(|(n, text)| {
            Self::parse(text, &format!("config/profiles/{n}.toml"))
                .expect("built-in profiles are valid")
        })
    }

    /// Every built-in profile, in the order they claim USB IDs.
    pub fn built_ins() -> Vec<Self> {
        BUILT_IN
            .iter()
            .filter_map(|(n, _)| Self::built_in(n))
            .collect()
    }

    /// The profile `name_or_path` names: a path to a TOML file (it contains `/` or ends in
    /// `.toml`), else `NAME.toml` in `dir` (the user's profiles), else a built-in profile.
    ///
    /// # Errors
    /// [`ProfileError::Unknown`] when nothing has the name, [`ProfileError::Read`] for a file
    /// that cannot be read, and those of [`Profile::parse`].
    pub fn load(name_or_path: &str, dir: &Path) -> Result<Self, ProfileError> {
        let is_path = name_or_path.contains('/') || name_or_path.ends_with(".toml");
        let path = if is_path {
            PathBuf::from(name_or_path)
        } else {
            dir.join(format!("{name_or_path}.toml"))
        };
        if !is_path && !path.is_file() {
            return Self::built_in(name_or_path).ok_or_else(|| ProfileError::Unknown {
                name: name_or_path.to_string(),
                dir: dir.to_path_buf(),
            });
        }
        let text = crate::sys::read_text(&path).map_err(|source| ProfileError::Read {
            path: path.clone(),
            source,
        })?;
        Self::parse(&text, &path.display().to_string())
    }

    /// The profile for the device `spec`: for the simulated v1 devices the configured one if
    /// it speaks protocol v1, else [`PHANTOM_PROFILE`] for `sim:phantom`, [`DELTA_PROFILE`] for
    /// `sim:delta` and [`CARTESIAN_V1`] for `sim:point-mass`; else the configured one
    /// (`device.profile`, which `--profile` sets); else the first profile claiming a HID
    /// device's USB IDs (the user's, by name, then the built-in ones), `woodenhaptics_v2015`
    /// for `sim:woodenhaptics`, and [`CARTESIAN_V1`] for anything else.
    ///
    /// # Errors
    /// Those of [`Profile::load`].
    pub fn for_device(spec: &DeviceSpec, config: &Config) -> Result<Self, ProfileError> {
        let dir = config.profile_dir();
        let configured = !config.device.profile.is_empty();
        match spec {
            // The other simulated devices' firmware speaks protocol v1: a configured profile
            // counts only if it does too (it may name another arm).
            DeviceSpec::Sim { model } if model != crate::config::SIM_WOODENHAPTICS => {
                if configured {
                    let profile = Self::load(&config.device.profile, &dir)?;
                    if profile.wire == Wire::CartesianV1 {
                        return Ok(profile);
                    }
                }
                Ok(match model.as_str() {
                    "phantom" => Self::built_in(PHANTOM_PROFILE).expect("built in"),
                    "delta" => Self::built_in(DELTA_PROFILE).expect("built in"),
                    _ => Self::cartesian(),
                })
            }
            _ if configured => Self::load(&config.device.profile, &dir),
            DeviceSpec::Hid { vid, pid, .. } => Ok(Self::all(&dir)?
                .into_iter()
                .find(|p| p.usb_ids.contains(&(*vid, *pid)))
                .unwrap_or_else(Self::cartesian)),
            DeviceSpec::Sim { .. } => Ok(Self::built_in(SIM_PROFILE).expect("built in")),
            DeviceSpec::Socket { .. } => Ok(Self::cartesian()),
        }
    }

    /// The user's profiles in `dir` (by file name), then the built-in ones; a user's profile
    /// with a built-in one's name (an edited copy) takes that one's place.
    ///
    /// # Errors
    /// Those of [`Profile::load`] for a user's profile that does not load.
    pub fn all(dir: &Path) -> Result<Vec<Self>, ProfileError> {
        let mut names: Vec<PathBuf> = std::fs::read_dir(dir)
            .map(|entries| {
                entries
                    .filter_map(|e| e.ok().map(|e| e.path()))
                    .filter(|p| p.extension().is_some_and(|e| e == "toml"))
                    .collect()
            })
            .unwrap_or_default();
        names.sort();
        let mut built_ins = Self::built_ins();
        let mut all = Vec::new();
        for path in &names {
            let profile = Self::load(&path.display().to_string(), dir)?;
            match built_ins.iter_mut().find(|b| b.name == profile.name) {
                Some(built_in) => *built_in = profile,
                None => all.push(profile),
            }
        }
        all.extend(built_ins);
        Ok(all)
    }

    /// The default profile.
    pub fn cartesian() -> Self {
        Self::built_in(CARTESIAN_V1).expect("built in")
    }

    /// The arm whose gravity the host can model (`[arm]`, or a joint-space profile's
    /// kinematics): None for a device the host knows only as Cartesian reports.
    pub fn gravity_arm(&self) -> Option<Arm> {
        self.gravity_arm
    }

    /// The arm's kinematics, for a joint-space profile.
    pub fn arm(&self) -> Option<&ArmModel> {
        self.arm.as_ref()
    }

    /// What a joint-space device cannot say about itself, from its profile, as a device-info
    /// report would: the profile's name as the model, a box about the workspace's sphere, the
    /// force limit, the servo rate `rate_hz`. None for a device that describes itself.
    pub fn device_info(&self, rate_hz: f64) -> Option<DeviceInfo> {
        let arm = self.arm.as_ref()?;
        Some(DeviceInfo {
            model: self.name.clone(),
            serial: String::new(),
            workspace_centre: Vector3::zeros(),
            workspace_half_extents: Vector3::repeat(arm.workspace_radius),
            max_force: self.max_force?,
            rate_hz,
            lockstep: false,
        })
    }

    /// The host side of this profile in the servo loop.
    pub fn codec(&self) -> Codec {
        match &self.arm {
            None => Codec::Cartesian,
            Some(arm) => Codec::Joint(JointCodec::new(*arm)),
        }
    }
}

/// One input report in the loop's terms.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sample {
    /// The report's sequence number; a protocol without one numbers reports as they come (the
    /// host cannot tell it missed one).
    pub sequence: u16,
    /// The device clock, µs; None for a protocol without one (the host's clock stands in).
    pub timestamp_us: Option<u32>,
    /// Handle position, device frame, m.
    pub position: Vector3<f64>,
    pub status: Status,
}

/// Between report bytes and the servo loop's SI quantities.
// One per servo loop, built before it starts: its size costs nothing, a box would cost a pointer
// chase per tick.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Debug)]
pub enum Codec {
    /// Protocol v1 carries positions and forces already.
    Cartesian,
    /// A joint-space device: kinematics on the host.
    Joint(JointCodec),
}

impl Codec {
    /// Decode an input report.
    ///
    /// # Errors
    /// The [`ProtocolError`] of a report that does not decode.
    pub fn decode(&mut self, bytes: &[u8]) -> Result<Sample, ProtocolError> {
        match self {
            Codec::Cartesian => {
                let r = InputReport::decode(bytes)?;
                Ok(Sample {
                    sequence: r.sequence,
                    timestamp_us: Some(r.timestamp_us),
                    position: r.position,
                    status: r.status,
                })
            }
            Codec::Joint(j) => j.decode(bytes),
        }
    }

    /// Encode the output report that renders `force` (N, finite, already limited) with motors
    /// `enable`d into `out`; returns its length. A force the report cannot carry becomes zero.
    pub fn encode(
        &mut self,
        sequence: u16,
        force: &Vector3<f64>,
        enable: bool,
        out: &mut [u8; OUTPUT_REPORT_LEN],
    ) -> usize {
        match self {
            Codec::Cartesian => {
                let report = OutputReport {
                    sequence,
                    force: *force,
                    enable,
                };
                if report.encode(out).is_err() {
                    OutputReport::zero(sequence)
                        .encode(out)
                        .expect("zero force always encodes");
                }
                OUTPUT_REPORT_LEN
            }
            Codec::Joint(j) => j.encode(force, enable, out),
        }
    }
}

/// The host side of a WoodenHaptics-protocol device: counts to position with the arm's forward
/// kinematics, force to clamped motor currents through Jᵀ at the last position read, and the
/// firmware's calibration request answered by homing the counters to the profile's
/// `home_counts`.
#[derive(Clone, Debug)]
pub struct JointCodec {
    arm: ArmModel,
    /// Joint angles of the last report, rad.
    angles: Vector3<f64>,
    /// Reports decoded, as the sequence number the protocol lacks.
    received: u16,
    /// The last report asked for its counters to be homed.
    homing: bool,
    /// Motors enabled by the last output report.
    enabled: bool,
}

impl JointCodec {
    pub fn new(arm: ArmModel) -> Self {
        Self {
            arm,
            angles: Vector3::zeros(),
            received: 0,
            homing: false,
            enabled: false,
        }
    }

    fn decode(&mut self, bytes: &[u8]) -> Result<Sample, ProtocolError> {
        let report = EncoderReport::decode(bytes)?;
        let counts = [report.counts[0], report.counts[1], report.counts[2]];
        self.angles = self.arm.angles(&counts);
        self.homing = report.calibration_requested();
        let sequence = self.received;
        self.received = self.received.wrapping_add(1);
        Ok(Sample {
            sequence,
            timestamp_us: None,
            position: self.arm.handle(&self.angles).position,
            // Counters not yet homed read positions relative to where the arm was at power-on:
            // a fault until the host has set them.
            status: Status::default()
                .with(Status::MOTORS_ENABLED, self.enabled)
                .with(Status::FAULT, self.homing),
        })
    }

    /// The currents, mA, that render `force` at the last position read, each clamped to the
    /// amplifier's full scale.
    fn milliamps(&self, force: &Vector3<f64>) -> [i16; 3] {
        let limit = self.arm.max_current * 1e3;
        let amps = self.arm.currents(&self.angles, force) * 1e3;
        amps.map(|ma| {
            if ma.is_finite() {
                ma.clamp(-limit, limit).round() as i16
            } else {
                0
            }
        })
        .into()
    }

    fn encode(
        &mut self,
        force: &Vector3<f64>,
        enable: bool,
        out: &mut [u8; OUTPUT_REPORT_LEN],
    ) -> usize {
        let report = if self.homing {
            self.homing = false;
            CurrentReport::set_encoders(self.arm.home_counts)
        } else if enable {
            CurrentReport::currents(self.milliamps(force))
        } else {
            CurrentReport::currents([0; 3])
        };
        self.enabled = enable;
        let mut bytes = [0; REPORT_LEN];
        report.encode(&mut bytes);
        out[..REPORT_LEN].copy_from_slice(&bytes);
        REPORT_LEN
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Issue 40: `lengths_m` with four elements and `counts_per_rev = [2000.5, …]` were
    /// accepted. An array has the length its key documents; counts are whole.
    #[test]
    fn arrays_have_their_documented_length_and_counts_are_whole() {
        let shipped = include_str!("../../config/profiles/woodenhaptics_v2015.toml");
        assert!(Profile::parse(shipped, "t").is_ok());
        for (from, to, says) in [
            (
                "lengths_m = [0.080, 0.205, 0.245]",
                "lengths_m = [0.080, 0.205, 0.245, 0.1]",
                "lengths_m",
            ),
            (
                "lengths_m = [0.080, 0.205, 0.245]",
                "lengths_m = [0.080, 0.205]",
                "lengths_m",
            ),
            (
                "counts_per_rev = [2000, 2000, 2000]",
                "counts_per_rev = [2000.5, 2000, 2000]",
                "kinematics.counts_per_rev: 2000.5 is not a whole number of counts",
            ),
        ] {
            assert!(shipped.contains(from), "{from}");
            let e = Profile::parse(&shipped.replace(from, to), "t")
                .unwrap_err()
                .to_string();
            assert!(e.contains(says), "{to}: {e}");
            assert_eq!(e.lines().count(), 1, "{e}");
        }
    }

    fn wooden() -> Profile {
        Profile::built_in("woodenhaptics_v2015").unwrap()
    }

    #[test]
    fn the_built_in_profiles_load_and_claim_the_published_usb_ids() {
        let all = Profile::built_ins();
        assert_eq!(all.len(), 5);
        assert_eq!(all[0].wire, Wire::CartesianV1);
        assert!(all[0].gravity_arm().is_none());
        for p in &all[1..3] {
            assert_eq!(p.wire, Wire::WoodenHaptics);
            assert_eq!(p.usb_ids, [(0x1234, 0x0006)]);
            assert!(p.device_info(1000.0).is_some());
            assert_eq!(p.gravity_arm().unwrap().kind(), "serial");
        }
        // The simulated arms' profiles: Cartesian reports, an arm, no USB IDs claimed.
        for (p, kind) in all[3..].iter().zip(["serial", "delta"]) {
            assert_eq!(p.wire, Wire::CartesianV1);
            assert!(p.usb_ids.is_empty() && p.device_info(1000.0).is_none());
            assert_eq!(p.gravity_arm().unwrap().kind(), kind);
        }
        assert!(all[0].device_info(1000.0).is_none());
    }

    #[test]
    fn a_profile_out_of_range_or_incomplete_is_refused_naming_the_key() {
        let text = include_str!("../../config/profiles/woodenhaptics_v2015.toml");
        let bad = text.replace("max_current_a = 6.0", "max_current_a = 600.0");
        let err = Profile::parse(&bad, "x.toml").unwrap_err().to_string();
        assert!(err.contains("`kinematics.max_current_a` = 600"), "{err}");
        let bad = text.replace("max_current_a = 6.0\n", "");
        let err = Profile::parse(&bad, "x.toml").unwrap_err().to_string();
        assert!(err.contains("max_current_a"), "{err}");
        let bad = text.replace("[\"1234:0006\"]", "[\"12340006\"]");
        let err = Profile::parse(&bad, "x.toml").unwrap_err().to_string();
        assert!(err.contains("usb_ids"), "{err}");
    }

    /// `[geometry_tolerances]`: read in SI, a key left out keeping the default, checked against
    /// its range, refused without an arm.
    #[test]
    fn geometry_tolerances_are_read_checked_and_need_an_arm() {
        let delta = include_str!("../../config/profiles/falcon_delta.toml");
        let shipped = Profile::parse(delta, "x.toml").unwrap();
        assert_eq!(shipped.geometry_tolerances, GeometryTolerances::DEFAULT);
        let with = |table: &str| format!("{delta}\n[geometry_tolerances]\n{table}");
        let p = Profile::parse(&with("origin_m = 0.0\nlength_share = 0.002\n"), "x.toml").unwrap();
        assert_eq!(
            p.geometry_tolerances,
            GeometryTolerances {
                origin: 0.0,
                length: 0.002,
                radius: GeometryTolerances::DEFAULT.radius
            }
        );
        for (table, key) in [
            ("origin_m = 0.5\n", "geometry_tolerances.origin_m"),
            ("length_share = -0.01\n", "geometry_tolerances.length_share"),
            (
                "pivot_radius_m = nan\n",
                "geometry_tolerances.pivot_radius_m",
            ),
            ("radius_m = 0.001\n", "radius_m"),
        ] {
            let err = Profile::parse(&with(table), "x.toml")
                .unwrap_err()
                .to_string();
            assert!(err.contains(key), "{table}: {err}");
        }
        let cartesian = include_str!("../../config/profiles/cartesian-v1.toml");
        let err = Profile::parse(
            &format!("{cartesian}\n[geometry_tolerances]\norigin_m = 0.001\n"),
            "x.toml",
        )
        .unwrap_err()
        .to_string();
        assert!(err.contains("without an arm"), "{err}");
    }

    #[test]
    fn the_profile_follows_the_config_then_the_usb_ids_then_the_default() {
        let dir = tempfile::tempdir().unwrap();
        let mut config = Config::default();
        config.paths.profile_dir = Some(dir.path().to_path_buf());
        let hid = |vid, pid| DeviceSpec::Hid {
            vid,
            pid,
            serial: None,
        };
        let name =
            |spec: &DeviceSpec, config: &Config| Profile::for_device(spec, config).unwrap().name;
        assert_eq!(name(&hid(0x1234, 6), &config), "woodenhaptics_v2015");
        assert_eq!(name(&hid(0x1209, 0x4847), &config), CARTESIAN_V1);
        assert_eq!(
            name(&"sim:woodenhaptics".parse().unwrap(), &config),
            "woodenhaptics_v2015"
        );
        assert_eq!(
            name(&"sim:phantom".parse().unwrap(), &config),
            PHANTOM_PROFILE
        );
        assert_eq!(name(&"sim:delta".parse().unwrap(), &config), DELTA_PROFILE);
        assert_eq!(
            name(&"sim:point-mass".parse().unwrap(), &config),
            CARTESIAN_V1
        );
        // A user's profile claims the IDs before the built-in ones.
        let mine = include_str!("../../config/profiles/polhem_v1.toml")
            .replace("name = \"polhem_v1\"", "name = \"my-polhem\"");
        std::fs::write(dir.path().join("my-polhem.toml"), mine).unwrap();
        assert_eq!(name(&hid(0x1234, 6), &config), "my-polhem");
        // Copies of the built-in profiles (the repository's config/profiles) change no order.
        let copies = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/profiles");
        config.paths.profile_dir = Some(copies);
        assert_eq!(name(&hid(0x1234, 6), &config), "woodenhaptics_v2015");
        assert_eq!(
            Profile::all(config.paths.profile_dir.as_ref().unwrap())
                .unwrap()
                .len(),
            5
        );
        config.device.profile = "polhem_v1".into();
        assert_eq!(name(&hid(0x1234, 6), &config), "polhem_v1");
        // A simulated v1 device takes a configured profile only if it speaks v1 too.
        assert_eq!(name(&"sim:delta".parse().unwrap(), &config), DELTA_PROFILE);
        config.device.profile = PHANTOM_PROFILE.into();
        assert_eq!(
            name(&"sim:delta".parse().unwrap(), &config),
            PHANTOM_PROFILE
        );
        config.device.profile = "nope".into();
        let err = Profile::for_device(&hid(0x1234, 6), &config).unwrap_err();
        assert!(
            err.to_string().contains("no device profile `nope`"),
            "{err}"
        );
    }

    #[test]
    fn the_joint_codec_reads_positions_and_writes_clamped_currents() {
        let arm = *wooden().arm().unwrap();
        let mut codec = wooden().codec();
        // The arm at a workspace point, as counts.
        let x = Vector3::new(0.02, -0.03, 0.01);
        let q = arm.joints_at(&x).unwrap();
        let c = arm.counts(&q).map(f64::round);
        let mut bytes = [0; REPORT_LEN];
        EncoderReport {
            counts: [c[0] as i16, c[1] as i16, c[2] as i16, 0, 0, 0],
            info: 0,
        }
        .encode(&mut bytes);
        let s = codec.decode(&bytes).unwrap();
        assert!((s.position - x).norm() < 1e-4, "{:?}", s.position);
        assert!(!s.status.contains(Status::FAULT));
        let mut out = [0; OUTPUT_REPORT_LEN];
        let n = codec.encode(0, &Vector3::new(0.0, 0.0, 1.0), true, &mut out);
        assert_eq!(n, REPORT_LEN);
        let sent = CurrentReport::decode(&out[..n]).unwrap();
        assert_eq!(sent.command, woodenhaptics::COMMAND_CURRENTS);
        // The currents give back the force through J^-T.
        let amps = Vector3::from(sent.currents_ma.map(f64::from)) * 1e-3;
        let tau = arm.joint_torques(&amps);
        let force = arm
            .handle(&arm.angles(&[c[0] as i16, c[1] as i16, c[2] as i16]))
            .jacobian
            .transpose()
            .lu()
            .solve(&tau)
            .unwrap();
        assert!(
            (force - Vector3::new(0.0, 0.0, 1.0)).norm() < 0.01,
            "{force:?}"
        );
        // A force beyond the amplifiers' reach is clamped to full scale.
        codec.encode(1, &Vector3::new(0.0, 0.0, -1e4), true, &mut out);
        let sent = CurrentReport::decode(&out[..REPORT_LEN]).unwrap();
        assert!(sent.currents_ma.iter().any(|&ma| ma.abs() == 6000));
        assert!(sent.currents_ma.iter().all(|&ma| ma.abs() <= 6000));
        // Motors disabled: zero current.
        codec.encode(2, &Vector3::new(0.0, 0.0, 1.0), false, &mut out);
        assert_eq!(
            CurrentReport::decode(&out[..REPORT_LEN]).unwrap(),
            CurrentReport::default()
        );
    }

    #[test]
    fn a_calibration_request_is_a_fault_until_the_counters_are_homed() {
        let mut codec = wooden().codec();
        let mut bytes = [0; REPORT_LEN];
        EncoderReport {
            counts: [10, -20, 30, 0, 0, 0],
            info: 1,
        }
        .encode(&mut bytes);
        let s = codec.decode(&bytes).unwrap();
        assert!(s.status.contains(Status::FAULT));
        let mut out = [0; OUTPUT_REPORT_LEN];
        let n = codec.encode(0, &Vector3::zeros(), true, &mut out);
        assert_eq!(
            CurrentReport::decode(&out[..n]).unwrap(),
            CurrentReport::set_encoders([0, 0, 6000])
        );
        // The next report without the flag is no fault, and forces flow again.
        EncoderReport {
            counts: [0, 0, 6000, 0, 0, 0],
            info: 0,
        }
        .encode(&mut bytes);
        assert!(!codec.decode(&bytes).unwrap().status.contains(Status::FAULT));
        codec.encode(1, &Vector3::new(1.0, 0.0, 0.0), true, &mut out);
        let sent = CurrentReport::decode(&out[..REPORT_LEN]).unwrap();
        assert_eq!(sent.command, woodenhaptics::COMMAND_CURRENTS);
        assert_ne!(sent.currents_ma, [0; 3]);
    }
}
