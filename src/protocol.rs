//! HID report protocol v1: byte layout of the input report (device → host), the output report
//! (host → device) and the device-info feature report (device → host, on request), with a codec
//! that never panics. `docs/hid-protocol.md` is the normative text.
//!
//! All multi-byte fields are little-endian. Positions travel in nanometres (i32), forces in
//! micronewtons (i32); inside hgcd both are converted to metres and newtons at once.

use nalgebra::Vector3;
use thiserror::Error;

/// Protocol version carried in byte 1 of every report.
pub const PROTOCOL_VERSION: u8 = 1;
/// Report ID of the input report (device → host).
pub const INPUT_REPORT_ID: u8 = 0x01;
/// Report ID of the output report (host → device).
pub const OUTPUT_REPORT_ID: u8 = 0x02;
/// Length of an input report in bytes, report ID included.
pub const INPUT_REPORT_LEN: usize = 24;

/// Largest report a transport hands up; longer ones are cut and then rejected by the decoder.
pub const MAX_REPORT_LEN: usize = 64;
/// Length of an output report in bytes, report ID included.
pub const OUTPUT_REPORT_LEN: usize = 20;
/// Report ID of the device-info feature report (device → host, when the host asks).
pub const DEVICE_INFO_REPORT_ID: u8 = 0x03;
/// Length of the device-info report in bytes, report ID included.
pub const DEVICE_INFO_LEN: usize = 64;
/// Bytes the device-info report gives the model string (UTF-8, NUL-padded).
pub const MODEL_LEN: usize = 16;
/// Bytes the device-info report gives the serial-number string (UTF-8, NUL-padded).
pub const SERIAL_LEN: usize = 12;
/// Largest position magnitude per axis a report may carry, metres.
pub const MAX_POSITION: f64 = 1.0;
/// Largest force magnitude per axis a report may carry, newtons.
pub const MAX_FORCE: f64 = 100.0;

const NM_PER_M: f64 = 1e9;
const UN_PER_N: f64 = 1e6;
const MHZ_PER_HZ: f64 = 1e3;
/// Largest raw position, nm (±1 m).
const MAX_POSITION_NM: i64 = 1_000_000_000;
/// Largest raw force, µN (±100 N).
const MAX_FORCE_UN: i64 = 100_000_000;

/// Status flags of an input report (byte 20–21).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Status(u16);

impl Status {
    /// Motor amplifiers are powered and following force commands.
    pub const MOTORS_ENABLED: u16 = 1 << 0;
    /// The device detected a fault (over-current, over-temperature, encoder error) and holds zero force.
    pub const FAULT: u16 = 1 << 1;
    /// The handle's button is pressed.
    pub const BUTTON: u16 = 1 << 2;
    /// The last force command exceeded the device's limit and was clamped.
    pub const FORCE_SATURATED: u16 = 1 << 3;
    /// The device's own watchdog tripped: no output report for too long, force zeroed.
    pub const DEVICE_WATCHDOG: u16 = 1 << 4;
    /// Every defined bit; the others are reserved and must be zero.
    pub const DEFINED: u16 = 0x001f;

    /// Build from raw bits, rejecting reserved bits.
    ///
    /// # Errors
    /// [`ProtocolError::ReservedStatusBits`] when a reserved bit is set.
    pub fn from_bits(bits: u16) -> Result<Self, ProtocolError> {
        if bits & !Self::DEFINED != 0 {
            return Err(ProtocolError::ReservedStatusBits(bits));
        }
        Ok(Self(bits))
    }
    pub fn bits(self) -> u16 {
        self.0
    }
    pub fn contains(self, flag: u16) -> bool {
        self.0 & flag == flag
    }
    pub fn with(self, flag: u16, on: bool) -> Self {
        if on {
            Self(self.0 | flag)
        } else {
            Self(self.0 & !flag)
        }
    }
}

/// Device → host: one sample of the end-effector state, sent at the device's servo rate.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct InputReport {
    /// Increments by one per report, wrapping at 2^16; gaps mean the host missed reports.
    pub sequence: u16,
    /// Device clock in microseconds, wrapping at 2^32.
    pub timestamp_us: u32,
    /// End-effector position in the device's Cartesian frame, metres.
    pub position: Vector3<f64>,
    pub status: Status,
}

/// Host → device: the force to render until the next output report.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OutputReport {
    /// Increments by one per report, wrapping at 2^16.
    pub sequence: u16,
    /// Force on the end effector in the device's Cartesian frame, newtons.
    pub force: Vector3<f64>,
    /// Motors enabled; when false the device renders zero force whatever `force` says.
    pub enable: bool,
}

/// Why a report could not be decoded or encoded.
#[derive(Clone, Debug, Error, PartialEq)]
pub enum ProtocolError {
    #[error("report is {got} bytes, expected {expected}")]
    Length { got: usize, expected: usize },
    #[error("unknown report ID {0:#04x}")]
    UnknownReportId(u8),
    #[error("unsupported protocol version {0} (hgcd speaks version {PROTOCOL_VERSION})")]
    Version(u8),
    #[error("reserved status bits set: {0:#06x}")]
    ReservedStatusBits(u16),
    #[error("reserved output flag bits set: {0:#04x}")]
    ReservedFlagBits(u8),
    #[error("reserved bytes are not zero")]
    ReservedBytes,
    #[error("{quantity} on axis {axis} out of range: {value}")]
    OutOfRange {
        quantity: &'static str,
        axis: usize,
        value: f64,
    },
    /// A scalar of the device-info report outside its range (value in Hz or N).
    #[error("device-info {quantity} out of range: {value}")]
    InfoOutOfRange { quantity: &'static str, value: f64 },
    #[error("reserved device-info flag bits set: {0:#04x}")]
    ReservedInfoFlags(u8),
    /// A string field of the device-info report that is not what §5a allows.
    #[error("device-info {field} {problem}")]
    Text {
        field: &'static str,
        problem: &'static str,
    },
}

fn check_header(bytes: &[u8], id: u8, len: usize) -> Result<(), ProtocolError> {
    if bytes.len() != len {
        // A report with the wrong ID is reported as such even when its length differs too.
        if let Some(&first) = bytes.first() {
            if first != id {
                return Err(ProtocolError::UnknownReportId(first));
            }
        }
        return Err(ProtocolError::Length {
            got: bytes.len(),
            expected: len,
        });
    }
    if bytes[0] != id {
        return Err(ProtocolError::UnknownReportId(bytes[0]));
    }
    if bytes[1] != PROTOCOL_VERSION {
        return Err(ProtocolError::Version(bytes[1]));
    }
    Ok(())
}

fn read_i32(bytes: &[u8], at: usize) -> i32 {
    i32::from_le_bytes([bytes[at], bytes[at + 1], bytes[at + 2], bytes[at + 3]])
}

fn read_vector(
    bytes: &[u8],
    at: usize,
    scale: f64,
    limit: f64,
    quantity: &'static str,
) -> Result<Vector3<f64>, ProtocolError> {
    let mut v = Vector3::zeros();
    for axis in 0..3 {
        let value = f64::from(read_i32(bytes, at + 4 * axis)) / scale;
        if value.abs() > limit {
            return Err(ProtocolError::OutOfRange {
                quantity,
                axis,
                value,
            });
        }
        v[axis] = value;
    }
    Ok(v)
}

fn write_vector(
    out: &mut [u8],
    at: usize,
    v: &Vector3<f64>,
    scale: f64,
    limit: f64,
    quantity: &'static str,
) -> Result<(), ProtocolError> {
    for axis in 0..3 {
        let value = v[axis];
        if !value.is_finite() || value.abs() > limit {
            return Err(ProtocolError::OutOfRange {
                quantity,
                axis,
                value,
            });
        }
        let raw = (value * scale).round() as i32;
        out[at + 4 * axis..at + 4 * axis + 4].copy_from_slice(&raw.to_le_bytes());
    }
    Ok(())
}

impl InputReport {
    /// Decode an input report (report ID included as byte 0).
    ///
    /// # Errors
    /// [`ProtocolError::Length`], [`ProtocolError::UnknownReportId`] or [`ProtocolError::Version`]
    /// for a bad header, [`ProtocolError::OutOfRange`] for a position beyond ±[`MAX_POSITION`],
    /// [`ProtocolError::ReservedStatusBits`] or [`ProtocolError::ReservedBytes`] for reserved bits
    /// or bytes set.
    pub fn decode(bytes: &[u8]) -> Result<Self, ProtocolError> {
        check_header(bytes, INPUT_REPORT_ID, INPUT_REPORT_LEN)?;
        let sequence = u16::from_le_bytes([bytes[2], bytes[3]]);
        let timestamp_us = u32::from_le_bytes([bytes[4], bytes[5], bytes[6], bytes[7]]);
        let position = read_vector(bytes, 8, NM_PER_M, MAX_POSITION, "position")?;
        let status = Status::from_bits(u16::from_le_bytes([bytes[20], bytes[21]]))?;
        if bytes[22] != 0 || bytes[23] != 0 {
            return Err(ProtocolError::ReservedBytes);
        }
        Ok(Self {
            sequence,
            timestamp_us,
            position,
            status,
        })
    }

    /// Encode into `out`.
    ///
    /// # Errors
    /// [`ProtocolError::OutOfRange`] for a position outside ±[`MAX_POSITION`] or non-finite.
    pub fn encode(&self, out: &mut [u8; INPUT_REPORT_LEN]) -> Result<(), ProtocolError> {
        *out = [0; INPUT_REPORT_LEN];
        out[0] = INPUT_REPORT_ID;
        out[1] = PROTOCOL_VERSION;
        out[2..4].copy_from_slice(&self.sequence.to_le_bytes());
        out[4..8].copy_from_slice(&self.timestamp_us.to_le_bytes());
        write_vector(out, 8, &self.position, NM_PER_M, MAX_POSITION, "position")?;
        out[20..22].copy_from_slice(&self.status.bits().to_le_bytes());
        Ok(())
    }
}

impl OutputReport {
    /// Bit 0 of byte 16: motors enabled.
    pub const FLAG_ENABLE: u8 = 1 << 0;

    /// The report that commands zero force with motors enabled.
    pub fn zero(sequence: u16) -> Self {
        Self {
            sequence,
            force: Vector3::zeros(),
            enable: true,
        }
    }

    /// Decode an output report (what emulated device firmware does).
    ///
    /// # Errors
    /// [`ProtocolError::Length`], [`ProtocolError::UnknownReportId`] or [`ProtocolError::Version`]
    /// for a bad header, [`ProtocolError::OutOfRange`] for a force beyond ±[`MAX_FORCE`],
    /// [`ProtocolError::ReservedFlagBits`] or [`ProtocolError::ReservedBytes`] for reserved bits
    /// or bytes set.
    pub fn decode(bytes: &[u8]) -> Result<Self, ProtocolError> {
        check_header(bytes, OUTPUT_REPORT_ID, OUTPUT_REPORT_LEN)?;
        let sequence = u16::from_le_bytes([bytes[2], bytes[3]]);
        let force = read_vector(bytes, 4, UN_PER_N, MAX_FORCE, "force")?;
        let flags = bytes[16];
        if flags & !Self::FLAG_ENABLE != 0 {
            return Err(ProtocolError::ReservedFlagBits(flags));
        }
        if bytes[17..20].iter().any(|&b| b != 0) {
            return Err(ProtocolError::ReservedBytes);
        }
        Ok(Self {
            sequence,
            force,
            enable: flags & Self::FLAG_ENABLE != 0,
        })
    }

    /// Encode into `out`.
    ///
    /// # Errors
    /// [`ProtocolError::OutOfRange`] for a non-finite force or one outside ±[`MAX_FORCE`] per axis.
    pub fn encode(&self, out: &mut [u8; OUTPUT_REPORT_LEN]) -> Result<(), ProtocolError> {
        *out = [0; OUTPUT_REPORT_LEN];
        out[0] = OUTPUT_REPORT_ID;
        out[1] = PROTOCOL_VERSION;
        out[2..4].copy_from_slice(&self.sequence.to_le_bytes());
        write_vector(out, 4, &self.force, UN_PER_N, MAX_FORCE, "force")?;
        out[16] = if self.enable { Self::FLAG_ENABLE } else { 0 };
        Ok(())
    }
}

/// What a device says about itself in its device-info feature report (report ID
/// [`DEVICE_INFO_REPORT_ID`], `docs/hid-protocol.md` §5a): who it is, where its workspace lies and
/// what it can render. The host asks once, when it opens the device. A device profile (a device
/// that cannot answer, described by configuration) describes itself with the same type.
#[derive(Clone, Debug, PartialEq)]
pub struct DeviceInfo {
    /// Model name, not empty, without control characters: in a report at most [`MODEL_LEN`]
    /// bytes of UTF-8; from a profile its name.
    pub model: String,
    /// Serial number of this unit, at most [`SERIAL_LEN`] bytes; empty when the device has none.
    pub serial: String,
    /// Centre of the workspace box in the device frame, m.
    pub workspace_centre: Vector3<f64>,
    /// Half-extents of the workspace box along x, y and z, m (each positive).
    pub workspace_half_extents: Vector3<f64>,
    /// The largest force the device renders on an axis (its actuator limit, §7.4), N.
    pub max_force: f64,
    /// Native report rate, Hz.
    pub rate_hz: f64,
    /// The device advances one report period per host reply (lock-step socket devices, §9):
    /// its clock, not the wall clock, measures the run.
    pub lockstep: bool,
}

impl DeviceInfo {
    /// Bit 0 of byte 2: the device runs in lock-step with the host.
    pub const FLAG_LOCKSTEP: u8 = 1 << 0;

    /// The workspace box (smallest corner, largest corner), m.
    pub fn workspace(&self) -> (Vector3<f64>, Vector3<f64>) {
        (
            self.workspace_centre - self.workspace_half_extents,
            self.workspace_centre + self.workspace_half_extents,
        )
    }

    /// Decode a device-info report (report ID included as byte 0), with the checks of §5a.
    ///
    /// # Errors
    /// [`ProtocolError::Length`], [`ProtocolError::UnknownReportId`] or [`ProtocolError::Version`]
    /// for a bad header, [`ProtocolError::ReservedInfoFlags`] or [`ProtocolError::ReservedBytes`]
    /// for reserved bits or bytes set, [`ProtocolError::InfoOutOfRange`] for the report rate or
    /// force limit, [`ProtocolError::OutOfRange`] for the workspace box and
    /// [`ProtocolError::Text`] for the model or serial.
    pub fn decode(bytes: &[u8]) -> Result<Self, ProtocolError> {
        check_header(bytes, DEVICE_INFO_REPORT_ID, DEVICE_INFO_LEN)?;
        let flags = bytes[2];
        if flags & !Self::FLAG_LOCKSTEP != 0 {
            return Err(ProtocolError::ReservedInfoFlags(flags));
        }
        if bytes[3] != 0 {
            return Err(ProtocolError::ReservedBytes);
        }
        let rate_mhz = read_u32(bytes, 4);
        if rate_mhz == 0 {
            return Err(ProtocolError::InfoOutOfRange {
                quantity: "report rate",
                value: 0.0,
            });
        }
        let force_un = read_u32(bytes, 8);
        if force_un == 0 || i64::from(force_un) > MAX_FORCE_UN {
            return Err(ProtocolError::InfoOutOfRange {
                quantity: "force limit",
                value: f64::from(force_un) / UN_PER_N,
            });
        }
        let centre = read_vector(bytes, 12, NM_PER_M, MAX_POSITION, "workspace centre")?;
        let mut half = Vector3::zeros();
        for axis in 0..3 {
            let raw = i64::from(read_i32(bytes, 24 + 4 * axis));
            let centre_nm = i64::from(read_i32(bytes, 12 + 4 * axis));
            // Positive, and the box within the position range of the input report.
            if raw <= 0 || centre_nm.abs() + raw > MAX_POSITION_NM {
                return Err(ProtocolError::OutOfRange {
                    quantity: "workspace half-extent",
                    axis,
                    value: raw as f64 / NM_PER_M,
                });
            }
            half[axis] = raw as f64 / NM_PER_M;
        }
        let model = read_text(&bytes[36..36 + MODEL_LEN], "model")?;
        if model.is_empty() {
            return Err(ProtocolError::Text {
                field: "model",
                problem: "is empty",
            });
        }
        let serial = read_text(&bytes[36 + MODEL_LEN..], "serial")?;
        Ok(Self {
            model,
            serial,
            workspace_centre: centre,
            workspace_half_extents: half,
            max_force: f64::from(force_un) / UN_PER_N,
            rate_hz: f64::from(rate_mhz) / MHZ_PER_HZ,
            lockstep: flags & Self::FLAG_LOCKSTEP != 0,
        })
    }

    /// Encode into `out`.
    ///
    /// # Errors
    /// For a value the report cannot carry: those of [`DeviceInfo::decode`], and
    /// [`ProtocolError::Text`] for a string longer than its field.
    pub fn encode(&self, out: &mut [u8; DEVICE_INFO_LEN]) -> Result<(), ProtocolError> {
        *out = [0; DEVICE_INFO_LEN];
        out[0] = DEVICE_INFO_REPORT_ID;
        out[1] = PROTOCOL_VERSION;
        out[2] = if self.lockstep {
            Self::FLAG_LOCKSTEP
        } else {
            0
        };
        let rate_mhz = (self.rate_hz * MHZ_PER_HZ).round();
        if !(1.0..=f64::from(u32::MAX)).contains(&rate_mhz) {
            return Err(ProtocolError::InfoOutOfRange {
                quantity: "report rate",
                value: self.rate_hz,
            });
        }
        out[4..8].copy_from_slice(&(rate_mhz as u32).to_le_bytes());
        let force_un = (self.max_force * UN_PER_N).round();
        if !(1.0..=MAX_FORCE_UN as f64).contains(&force_un) {
            return Err(ProtocolError::InfoOutOfRange {
                quantity: "force limit",
                value: self.max_force,
            });
        }
        out[8..12].copy_from_slice(&(force_un as u32).to_le_bytes());
        write_vector(
            out,
            12,
            &self.workspace_centre,
            NM_PER_M,
            MAX_POSITION,
            "workspace centre",
        )?;
        write_vector(
            out,
            24,
            &self.workspace_half_extents,
            NM_PER_M,
            MAX_POSITION,
            "workspace half-extent",
        )?;
        write_text(&mut out[36..36 + MODEL_LEN], &self.model, "model")?;
        write_text(&mut out[36 + MODEL_LEN..], &self.serial, "serial")?;
        // What decoding checks beyond the field ranges (a positive box inside ±1 m, a model).
        Self::decode(out).map(|_| ())
    }
}

fn read_u32(bytes: &[u8], at: usize) -> u32 {
    u32::from_le_bytes([bytes[at], bytes[at + 1], bytes[at + 2], bytes[at + 3]])
}

/// A NUL-padded UTF-8 field: the text before the first NUL, which must be all that is not NUL.
fn read_text(field: &[u8], name: &'static str) -> Result<String, ProtocolError> {
    let problem = |problem| ProtocolError::Text {
        field: name,
        problem,
    };
    let end = field.iter().position(|&b| b == 0).unwrap_or(field.len());
    if field[end..].iter().any(|&b| b != 0) {
        return Err(problem("has bytes after its terminating NUL"));
    }
    let text = std::str::from_utf8(&field[..end]).map_err(|_| problem("is not UTF-8"))?;
    if text.chars().any(char::is_control) {
        return Err(problem("contains a control character"));
    }
    Ok(text.to_string())
}

fn write_text(field: &mut [u8], text: &str, name: &'static str) -> Result<(), ProtocolError> {
    if text.len() > field.len() {
        return Err(ProtocolError::Text {
            field: name,
            problem: "is longer than its field",
        });
    }
    field[..text.len()].copy_from_slice(text.as_bytes());
    Ok(())
}

/// Unwraps the device's 32-bit microsecond clock (§7.3) into seconds since the first report. The
/// result never runs backwards: a clock that jumps back (a device reset) just adds no time.
#[derive(Clone, Copy, Debug, Default)]
pub struct DeviceClock {
    last: Option<u32>,
    elapsed_us: u64,
}

impl DeviceClock {
    /// Seconds since the first report, and whether the clock just jumped back (a device reset).
    pub fn seconds(&mut self, raw: u32) -> (f64, bool) {
        let mut jumped_back = false;
        if let Some(last) = self.last {
            let step = raw.wrapping_sub(last);
            if step < u32::MAX / 2 {
                self.elapsed_us += u64::from(step);
            } else {
                jumped_back = true;
            }
        }
        self.last = Some(raw);
        (self.elapsed_us as f64 * 1e-6, jumped_back)
    }
}

/// The HID report descriptor a v1 device presents (vendor-defined usage page 0xFF00).
pub const REPORT_DESCRIPTOR: [u8; 31] = [
    0x06, 0x00, 0xFF, // Usage Page (Vendor Defined 0xFF00)
    0x09, 0x01, //       Usage (0x01: hgcd haptic device)
    0xA1, 0x01, //       Collection (Application)
    0x15, 0x00, //         Logical Minimum (0)
    0x26, 0xFF, 0x00, //   Logical Maximum (255)
    0x75, 0x08, //         Report Size (8)
    0x85, 0x01, //         Report ID (1): input report
    0x09, 0x02, //         Usage (0x02: state)
    0x95, 0x17, //         Report Count (23)
    0x81, 0x02, //         Input (Data, Variable, Absolute)
    0x85, 0x02, //         Report ID (2): output report
    0x09, 0x03, //         Usage (0x03: force command)
    0x95, 0x13, //         Report Count (19)
    0x91, 0x02, //         Output (Data, Variable, Absolute)
    0xC0, //             End Collection
];

/// The feature item a device that offers the device-info report adds (report ID 3, 63 bytes).
const DEVICE_INFO_ITEM: [u8; 8] = [
    0x85, 0x03, // Report ID (3): device-info feature report
    0x09, 0x04, // Usage (0x04: device info)
    0x95, 0x3F, // Report Count (63)
    0xB1, 0x02, // Feature (Data, Variable, Absolute)
];

/// The descriptor of a v1 device that also offers the device-info feature report: the v1
/// descriptor with the device-info feature item before its End Collection.
pub const REPORT_DESCRIPTOR_WITH_DEVICE_INFO: [u8; 39] = {
    let mut d = [0; 39];
    let end = REPORT_DESCRIPTOR.len() - 1;
    let mut i = 0;
    while i < end {
        d[i] = REPORT_DESCRIPTOR[i];
        i += 1;
    }
    while i < end + DEVICE_INFO_ITEM.len() {
        d[i] = DEVICE_INFO_ITEM[i - end];
        i += 1;
    }
    d[i] = REPORT_DESCRIPTOR[end];
    d
};

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn sample_input() -> InputReport {
        InputReport {
            sequence: 65535,
            timestamp_us: 4_000_000_123,
            position: Vector3::new(0.012345678, -0.5, 0.999999999),
            status: Status::from_bits(Status::MOTORS_ENABLED | Status::BUTTON).unwrap(),
        }
    }

    #[test]
    fn device_clock_unwraps() {
        let mut c = DeviceClock::default();
        assert_eq!(c.seconds(u32::MAX - 999), (0.0, false));
        assert!((c.seconds(u32::MAX).0 - 999e-6).abs() < 1e-12);
        assert!((c.seconds(1000).0 - 2000e-6).abs() < 1e-12);
        // A reset clock does not make time run backwards, and says it jumped.
        let (t, jumped) = c.seconds(10);
        assert!((t - 2000e-6).abs() < 1e-12 && jumped);
        assert_eq!(c.seconds(20), (2010e-6, false));
    }

    #[test]
    fn input_round_trip_is_exact_to_a_nanometre() {
        let r = sample_input();
        let mut buf = [0; INPUT_REPORT_LEN];
        r.encode(&mut buf).unwrap();
        let back = InputReport::decode(&buf).unwrap();
        assert_eq!(back.sequence, r.sequence);
        assert_eq!(back.timestamp_us, r.timestamp_us);
        assert_eq!(back.status, r.status);
        assert!((back.position - r.position).amax() <= 0.5e-9);
    }

    #[test]
    fn output_round_trip_and_layout() {
        let r = OutputReport {
            sequence: 0x1234,
            force: Vector3::new(1.5, -0.000001, 99.0),
            enable: true,
        };
        let mut buf = [0; OUTPUT_REPORT_LEN];
        r.encode(&mut buf).unwrap();
        assert_eq!(&buf[..4], &[0x02, 0x01, 0x34, 0x12]);
        assert_eq!(i32::from_le_bytes(buf[4..8].try_into().unwrap()), 1_500_000);
        assert_eq!(i32::from_le_bytes(buf[8..12].try_into().unwrap()), -1);
        assert_eq!(buf[16], 1);
        assert_eq!(OutputReport::decode(&buf).unwrap(), r);
    }

    #[test]
    fn typed_errors_for_bad_reports() {
        let mut buf = [0; INPUT_REPORT_LEN];
        sample_input().encode(&mut buf).unwrap();
        assert_eq!(
            InputReport::decode(&buf[..10]),
            Err(ProtocolError::Length {
                got: 10,
                expected: INPUT_REPORT_LEN
            })
        );
        let mut bad = buf;
        bad[0] = 0x07;
        assert_eq!(
            InputReport::decode(&bad),
            Err(ProtocolError::UnknownReportId(7))
        );
        let mut bad = buf;
        bad[1] = 2;
        assert_eq!(InputReport::decode(&bad), Err(ProtocolError::Version(2)));
        let mut bad = buf;
        bad[21] = 0x80;
        assert!(matches!(
            InputReport::decode(&bad),
            Err(ProtocolError::ReservedStatusBits(_))
        ));
        let mut bad = buf;
        bad[8..12].copy_from_slice(&i32::MAX.to_le_bytes());
        assert!(matches!(
            InputReport::decode(&bad),
            Err(ProtocolError::OutOfRange { axis: 0, .. })
        ));
        let nan = OutputReport {
            sequence: 0,
            force: Vector3::new(0.0, f64::NAN, 0.0),
            enable: true,
        };
        assert!(nan.encode(&mut [0; OUTPUT_REPORT_LEN]).is_err());
    }

    #[test]
    fn descriptor_report_counts_match_lengths() {
        // Report Count items give the payload without the report ID byte.
        assert_eq!(REPORT_DESCRIPTOR[19] as usize, INPUT_REPORT_LEN - 1);
        assert_eq!(REPORT_DESCRIPTOR[27] as usize, OUTPUT_REPORT_LEN - 1);
        // With device info: the same items, then report ID 3's feature item before the end.
        let with = REPORT_DESCRIPTOR_WITH_DEVICE_INFO;
        assert_eq!(with[..30], REPORT_DESCRIPTOR[..30]);
        assert_eq!(
            with[30..38],
            [
                0x85,
                DEVICE_INFO_REPORT_ID,
                0x09,
                0x04,
                0x95,
                0x3F,
                0xB1,
                0x02
            ]
        );
        assert_eq!(with[35] as usize, DEVICE_INFO_LEN - 1);
        assert_eq!(with[38], 0xC0);
    }

    /// The device-info report of `docs/hid-protocol.md` §8.4.
    fn example_info() -> DeviceInfo {
        DeviceInfo {
            model: "PHANToM-like 3".into(),
            serial: "SN-00042".into(),
            workspace_centre: Vector3::new(0.0, 0.15, 0.06),
            workspace_half_extents: Vector3::new(0.08, 0.06, 0.06),
            max_force: 3.0,
            rate_hz: 1000.0,
            lockstep: true,
        }
    }

    /// The bytes of §8.4, as the document prints them.
    const EXAMPLE_INFO_BYTES: &str = "03 01 01 00 40 42 0F 00 C0 C6 2D 00 00 00 00 00 80 D1 F0 08 \
        00 87 93 03 00 B4 C4 04 00 87 93 03 00 87 93 03 50 48 41 4E 54 6F 4D 2D 6C 69 6B 65 20 33 \
        00 00 53 4E 2D 30 30 30 34 32 00 00 00 00";

    fn hex(text: &str) -> Vec<u8> {
        text.split_whitespace()
            .map(|b| u8::from_str_radix(b, 16).unwrap())
            .collect()
    }

    #[test]
    fn device_info_matches_the_worked_example_byte_for_byte() {
        let bytes = hex(EXAMPLE_INFO_BYTES);
        assert_eq!(bytes.len(), DEVICE_INFO_LEN);
        let mut out = [0; DEVICE_INFO_LEN];
        example_info().encode(&mut out).unwrap();
        assert_eq!(out[..], bytes[..]);
        let back = DeviceInfo::decode(&bytes).unwrap();
        assert_eq!(back.model, "PHANToM-like 3");
        assert_eq!(back.serial, "SN-00042");
        assert!((back.workspace_centre - Vector3::new(0.0, 0.15, 0.06)).amax() < 1e-12);
        assert!((back.workspace_half_extents - Vector3::new(0.08, 0.06, 0.06)).amax() < 1e-12);
        assert_eq!(
            (back.max_force, back.rate_hz, back.lockstep),
            (3.0, 1000.0, true)
        );
        let (lo, hi) = back.workspace();
        assert!((lo - Vector3::new(-0.08, 0.09, 0.0)).amax() < 1e-12);
        assert!((hi - Vector3::new(0.08, 0.21, 0.12)).amax() < 1e-12);
    }

    #[test]
    fn typed_errors_for_bad_device_info() {
        let mut good = [0; DEVICE_INFO_LEN];
        example_info().encode(&mut good).unwrap();
        let with = |at: usize, value: &[u8]| {
            let mut b = good;
            b[at..at + value.len()].copy_from_slice(value);
            DeviceInfo::decode(&b)
        };
        assert_eq!(
            DeviceInfo::decode(&good[..20]),
            Err(ProtocolError::Length {
                got: 20,
                expected: DEVICE_INFO_LEN
            })
        );
        assert_eq!(with(0, &[0x02]), Err(ProtocolError::UnknownReportId(2)));
        assert_eq!(with(1, &[2]), Err(ProtocolError::Version(2)));
        assert_eq!(with(2, &[0x03]), Err(ProtocolError::ReservedInfoFlags(3)));
        assert_eq!(with(3, &[1]), Err(ProtocolError::ReservedBytes));
        assert_eq!(
            with(4, &[0; 4]),
            Err(ProtocolError::InfoOutOfRange {
                quantity: "report rate",
                value: 0.0
            })
        );
        assert_eq!(
            with(8, &100_000_001u32.to_le_bytes()),
            Err(ProtocolError::InfoOutOfRange {
                quantity: "force limit",
                value: 100.000001
            })
        );
        // A box reaching beyond ±1 m, an empty one.
        assert!(matches!(
            with(28, &960_000_000i32.to_le_bytes()),
            Err(ProtocolError::OutOfRange {
                quantity: "workspace half-extent",
                axis: 1,
                ..
            })
        ));
        assert!(matches!(
            with(32, &0i32.to_le_bytes()),
            Err(ProtocolError::OutOfRange {
                quantity: "workspace half-extent",
                axis: 2,
                ..
            })
        ));
        let text = |field, problem| Err(ProtocolError::Text { field, problem });
        assert_eq!(with(36, &[0; MODEL_LEN]), text("model", "is empty"));
        assert_eq!(with(36, &[0xff]), text("model", "is not UTF-8"));
        assert_eq!(
            with(36, b"\n"),
            text("model", "contains a control character")
        );
        assert_eq!(
            with(62, b"x"),
            text("serial", "has bytes after its terminating NUL")
        );
        // The encoder refuses what the decoder would.
        let refused = |info: DeviceInfo| info.encode(&mut [0; DEVICE_INFO_LEN]).unwrap_err();
        let long = DeviceInfo {
            serial: "0123456789ABC".into(),
            ..example_info()
        };
        assert_eq!(
            refused(long),
            ProtocolError::Text {
                field: "serial",
                problem: "is longer than its field"
            }
        );
        let nul = DeviceInfo {
            model: "a\0b".into(),
            ..example_info()
        };
        assert!(matches!(
            refused(nul),
            ProtocolError::Text { field: "model", .. }
        ));
        let flat = DeviceInfo {
            workspace_half_extents: Vector3::new(0.1, 0.0, 0.1),
            ..example_info()
        };
        assert!(matches!(
            refused(flat),
            ProtocolError::OutOfRange { axis: 1, .. }
        ));
        let slow = DeviceInfo {
            rate_hz: f64::NAN,
            ..example_info()
        };
        assert!(matches!(
            refused(slow),
            ProtocolError::InfoOutOfRange {
                quantity: "report rate",
                ..
            }
        ));
    }

    /// The rules of the v1 input report, written out independently of the decoder.
    fn valid_input(bytes: &[u8]) -> bool {
        bytes.len() == INPUT_REPORT_LEN
            && bytes[0] == INPUT_REPORT_ID
            && bytes[1] == PROTOCOL_VERSION
            && (0..3).all(|axis| read_i32(bytes, 8 + 4 * axis).unsigned_abs() <= 1_000_000_000)
            && u16::from_le_bytes([bytes[20], bytes[21]]) & !Status::DEFINED == 0
            && bytes[22..].iter().all(|&b| b == 0)
    }

    /// The rules of the v1 output report, written out independently of the decoder.
    fn valid_output(bytes: &[u8]) -> bool {
        bytes.len() == OUTPUT_REPORT_LEN
            && bytes[0] == OUTPUT_REPORT_ID
            && bytes[1] == PROTOCOL_VERSION
            && (0..3).all(|axis| read_i32(bytes, 4 + 4 * axis).unsigned_abs() <= 100_000_000)
            && bytes[16] & !OutputReport::FLAG_ENABLE == 0
            && bytes[17..].iter().all(|&b| b == 0)
    }

    /// The rules of the device-info report, written out independently of the decoder.
    fn valid_info(bytes: &[u8]) -> bool {
        let text = |field: &[u8], may_be_empty: bool| {
            let end = field.iter().position(|&b| b == 0).unwrap_or(field.len());
            field[end..].iter().all(|&b| b == 0)
                && (may_be_empty || end > 0)
                && std::str::from_utf8(&field[..end])
                    .is_ok_and(|t| !t.chars().any(char::is_control))
        };
        bytes.len() == DEVICE_INFO_LEN
            && bytes[0] == DEVICE_INFO_REPORT_ID
            && bytes[1] == PROTOCOL_VERSION
            && bytes[2] & !DeviceInfo::FLAG_LOCKSTEP == 0
            && bytes[3] == 0
            && read_u32(bytes, 4) > 0
            && (1..=100_000_000).contains(&read_u32(bytes, 8))
            && (0..3).all(|axis| {
                let c = i64::from(read_i32(bytes, 12 + 4 * axis));
                let h = i64::from(read_i32(bytes, 24 + 4 * axis));
                c.abs() <= 1_000_000_000 && h > 0 && c.abs() + h <= 1_000_000_000
            })
            && text(&bytes[36..52], false)
            && text(&bytes[52..64], true)
    }

    fn check_info(bytes: &[u8]) -> Result<(), TestCaseError> {
        let decoded = DeviceInfo::decode(bytes);
        prop_assert_eq!(decoded.is_ok(), valid_info(bytes), "{:?}", decoded);
        if let Ok(info) = decoded {
            let mut again = [0; DEVICE_INFO_LEN];
            info.encode(&mut again).unwrap();
            prop_assert_eq!(&again[..], bytes);
        }
        Ok(())
    }

    /// A valid device-info report's bytes: any flags, rate, limit and box in range (edges
    /// included), and strings of any allowed length.
    fn valid_info_bytes() -> impl Strategy<Value = Vec<u8>> {
        let centre = prop_oneof![-500_000_000i32..=500_000_000, Just(0)];
        let half = prop_oneof![1i32..=500_000_000, Just(1), Just(500_000_000)];
        (
            any::<bool>(),
            1u32..,
            prop_oneof![1u32..=100_000_000, Just(100_000_000)],
            [centre.clone(), centre.clone(), centre],
            [half.clone(), half.clone(), half],
            "[a-zA-Z0-9 ._é-]{1,7}",
            "[A-Z0-9-]{0,12}",
        )
            .prop_map(|(lockstep, rate, force, c, h, model, serial)| {
                let mut b = vec![
                    DEVICE_INFO_REPORT_ID,
                    PROTOCOL_VERSION,
                    u8::from(lockstep),
                    0,
                ];
                b.extend_from_slice(&rate.to_le_bytes());
                b.extend_from_slice(&force.to_le_bytes());
                for v in c.iter().chain(&h) {
                    b.extend_from_slice(&v.to_le_bytes());
                }
                let mut text = |t: &str, len: usize| {
                    let mut field = t.as_bytes().to_vec();
                    field.resize(len, 0);
                    b.extend_from_slice(&field);
                };
                text(&model, MODEL_LEN);
                text(&serial, SERIAL_LEN);
                b
            })
    }

    /// What the decoder accepted is in range, and encodes back to the very same bytes.
    fn check_input(bytes: &[u8]) -> Result<(), TestCaseError> {
        let decoded = InputReport::decode(bytes);
        prop_assert_eq!(decoded.is_ok(), valid_input(bytes), "{:?}", decoded);
        if let Ok(r) = decoded {
            prop_assert!(r
                .position
                .iter()
                .all(|p| p.is_finite() && p.abs() <= MAX_POSITION));
            prop_assert_eq!(r.status.bits() & !Status::DEFINED, 0);
            let mut again = [0; INPUT_REPORT_LEN];
            r.encode(&mut again).unwrap();
            prop_assert_eq!(&again[..], bytes);
        }
        Ok(())
    }

    fn check_output(bytes: &[u8]) -> Result<(), TestCaseError> {
        let decoded = OutputReport::decode(bytes);
        prop_assert_eq!(decoded.is_ok(), valid_output(bytes), "{:?}", decoded);
        if let Ok(r) = decoded {
            prop_assert!(r
                .force
                .iter()
                .all(|f| f.is_finite() && f.abs() <= MAX_FORCE));
            let mut again = [0; OUTPUT_REPORT_LEN];
            r.encode(&mut again).unwrap();
            prop_assert_eq!(&again[..], bytes);
        }
        Ok(())
    }

    /// A valid report's bytes: any header fields, and per axis either any value in range or one
    /// at (or just beyond) the edge of the range.
    fn valid_input_bytes() -> impl Strategy<Value = Vec<u8>> {
        let axis = prop_oneof![
            -1_000_000_000i32..=1_000_000_000,
            Just(1_000_000_000),
            Just(-1_000_000_000),
        ];
        (
            any::<u16>(),
            any::<u32>(),
            [axis.clone(), axis.clone(), axis],
            0..=Status::DEFINED,
        )
            .prop_map(|(seq, ts, nm, bits)| {
                let mut b = vec![INPUT_REPORT_ID, PROTOCOL_VERSION];
                b.extend_from_slice(&seq.to_le_bytes());
                b.extend_from_slice(&ts.to_le_bytes());
                for v in nm {
                    b.extend_from_slice(&v.to_le_bytes());
                }
                b.extend_from_slice(&bits.to_le_bytes());
                b.extend_from_slice(&[0, 0]);
                b
            })
    }

    fn valid_output_bytes() -> impl Strategy<Value = Vec<u8>> {
        let axis = prop_oneof![
            -100_000_000i32..=100_000_000,
            Just(100_000_000),
            Just(-100_000_000),
        ];
        (
            any::<u16>(),
            [axis.clone(), axis.clone(), axis],
            any::<bool>(),
        )
            .prop_map(|(seq, un, enable)| {
                let mut b = vec![OUTPUT_REPORT_ID, PROTOCOL_VERSION];
                b.extend_from_slice(&seq.to_le_bytes());
                for v in un {
                    b.extend_from_slice(&v.to_le_bytes());
                }
                b.extend_from_slice(&[u8::from(enable), 0, 0, 0]);
                b
            })
    }

    /// `bytes` with a few bytes overwritten, single bits flipped, and its length changed.
    fn mutated(bytes: impl Strategy<Value = Vec<u8>>) -> impl Strategy<Value = Vec<u8>> {
        let edit = (any::<prop::sample::Index>(), any::<u8>(), any::<bool>());
        (
            bytes,
            proptest::collection::vec(edit, 0..4),
            prop_oneof![3 => Just(None), 1 => (0usize..32).prop_map(Some)],
            any::<u8>(),
        )
            .prop_map(|(mut b, edits, resize, fill)| {
                for (at, value, flip_one_bit) in edits {
                    let i = at.index(b.len());
                    b[i] = if flip_one_bit {
                        b[i] ^ (1 << (value % 8))
                    } else {
                        value
                    };
                }
                if let Some(len) = resize {
                    b.resize(len, fill);
                }
                b
            })
    }

    proptest! {
        #![proptest_config(fuzz::config())]

        #[test]
        fn arbitrary_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..=64)) {
            check_input(&bytes)?;
            check_output(&bytes)?;
            check_info(&bytes)?;
        }

        #[test]
        fn mutated_device_info_reports_are_refused_or_exact(bytes in mutated(valid_info_bytes())) {
            check_info(&bytes)?;
        }

        #[test]
        fn mutated_input_reports_are_refused_or_exact(bytes in mutated(valid_input_bytes())) {
            check_input(&bytes)?;
        }

        #[test]
        fn mutated_output_reports_are_refused_or_exact(bytes in mutated(valid_output_bytes())) {
            check_output(&bytes)?;
        }

        #[test]
        fn valid_inputs_round_trip(seq in any::<u16>(), ts in any::<u32>(),
                                   x in -1.0f64..1.0, y in -1.0f64..1.0, z in -1.0f64..1.0,
                                   bits in 0u16..=Status::DEFINED) {
            let r = InputReport { sequence: seq, timestamp_us: ts, position: Vector3::new(x, y, z),
                                  status: Status::from_bits(bits).unwrap() };
            let mut buf = [0; INPUT_REPORT_LEN];
            r.encode(&mut buf).unwrap();
            let back = InputReport::decode(&buf).unwrap();
            prop_assert!((back.position - r.position).amax() <= 0.5e-9);
            prop_assert_eq!(back.status, r.status);
            prop_assert_eq!(back.sequence, seq);
            prop_assert_eq!(back.timestamp_us, ts);
        }

        #[test]
        fn valid_outputs_round_trip(seq in any::<u16>(), x in -100.0f64..100.0, y in -100.0f64..100.0,
                                    z in -100.0f64..100.0, enable in any::<bool>()) {
            let r = OutputReport { sequence: seq, force: Vector3::new(x, y, z), enable };
            let mut buf = [0; OUTPUT_REPORT_LEN];
            r.encode(&mut buf).unwrap();
            let back = OutputReport::decode(&buf).unwrap();
            prop_assert!((back.force - r.force).amax() <= 0.5e-6);
            prop_assert_eq!(back.enable, enable);
        }
    }
}

#[cfg(test)]
pub(crate) mod fuzz;
