//! HID report protocol v1: byte layout of the input report (device → host) and the output report
//! (host → device), with a codec that never panics. `docs/hid-protocol.md` is the normative text.
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
/// Largest position magnitude per axis a report may carry, metres.
pub const MAX_POSITION: f64 = 1.0;
/// Largest force magnitude per axis a report may carry, newtons.
pub const MAX_FORCE: f64 = 100.0;

const NM_PER_M: f64 = 1e9;
const UN_PER_N: f64 = 1e6;

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

    /// Encode into `out`; fails only for a position outside ±[`MAX_POSITION`] or non-finite.
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

    /// Encode into `out`; fails for a non-finite force or one outside ±[`MAX_FORCE`] per axis.
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
        fn arbitrary_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..64)) {
            check_input(&bytes)?;
            check_output(&bytes)?;
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

/// Settings shared by the fuzz properties of the wire codecs (`docs/fuzzing.md`).
#[cfg(test)]
pub(crate) mod fuzz {
    use proptest::test_runner::Config;

    /// Cases per property in a plain `cargo test`.
    pub const DEFAULT_CASES: u32 = 4096;

    /// `DEFAULT_CASES` cases, or `PROPTEST_CASES` when it is set (a long campaign).
    pub fn config() -> Config {
        let mut config = Config::default();
        if std::env::var_os("PROPTEST_CASES").is_none() {
            config.cases = DEFAULT_CASES;
        }
        config
    }
}
