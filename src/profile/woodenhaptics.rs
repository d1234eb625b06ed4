//! The WoodenHaptics / Polhem USB HID protocol (`docs/devices.md` §1): one 14-byte report each
//! way, no report ID, seven little-endian `int16` fields each. The device sends its encoder
//! counts and a calibration-request flag; the host answers with three motor currents in mA and a
//! command. A codec that never panics; the host side of the profile ([`super::JointCodec`]) and
//! the emulated firmware (`sim::woodenhaptics`) both speak through it.

use crate::protocol::ProtocolError;

/// USB vendor ID of the published firmware.
pub const VENDOR_ID: u16 = 0x1234;
/// USB product ID of the published firmware.
pub const PRODUCT_ID: u16 = 0x0006;
/// Length of either report, bytes (no report ID).
pub const REPORT_LEN: usize = 14;
/// The firmware zeroes its motors when no output report has come for this long, s.
pub const FIRMWARE_WATCHDOG: f64 = 0.5;
/// Command 0: render the three motor currents.
pub const COMMAND_CURRENTS: i16 = 0;
/// Command 1: set the encoder counters (a, b, c from the attributes; d, e, f from the current
/// fields) and clear the calibration request; the motors render nothing for that report.
pub const COMMAND_SET_ENCODERS: i16 = 1;

fn field(bytes: &[u8], n: usize) -> i16 {
    i16::from_le_bytes([bytes[2 * n], bytes[2 * n + 1]])
}

fn put(out: &mut [u8; REPORT_LEN], n: usize, value: i16) {
    out[2 * n..2 * n + 2].copy_from_slice(&value.to_le_bytes());
}

fn check_length(bytes: &[u8]) -> Result<(), ProtocolError> {
    if bytes.len() == REPORT_LEN {
        Ok(())
    } else {
        Err(ProtocolError::Length {
            got: bytes.len(),
            expected: REPORT_LEN,
        })
    }
}

/// Device → host: the six encoder counters (a, b, c drive the arm; d, e, f are an optional
/// gimbal's) and the info field.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct EncoderReport {
    pub counts: [i16; 6],
    /// Non-zero: the calibration switch was pressed and the counters have not been set since
    /// (the host should home them with [`COMMAND_SET_ENCODERS`]).
    pub info: i16,
}

impl EncoderReport {
    /// Decode the 14 bytes of an input report.
    ///
    /// # Errors
    /// [`ProtocolError::Length`] for any other length.
    pub fn decode(bytes: &[u8]) -> Result<Self, ProtocolError> {
        check_length(bytes)?;
        let mut counts = [0; 6];
        for (n, c) in counts.iter_mut().enumerate() {
            *c = field(bytes, n);
        }
        Ok(Self {
            counts,
            info: field(bytes, 6),
        })
    }

    pub fn encode(&self, out: &mut [u8; REPORT_LEN]) {
        for (n, c) in self.counts.iter().enumerate() {
            put(out, n, *c);
        }
        put(out, 6, self.info);
    }

    /// Whether the calibration switch asks for the counters to be homed.
    pub fn calibration_requested(&self) -> bool {
        self.info != 0
    }
}

/// Host → device: three motor currents in mA, a command and its three attributes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CurrentReport {
    pub currents_ma: [i16; 3],
    pub command: i16,
    pub attributes: [i16; 3],
}

impl CurrentReport {
    /// Render `currents_ma`.
    pub fn currents(currents_ma: [i16; 3]) -> Self {
        Self {
            currents_ma,
            ..Self::default()
        }
    }

    /// Set the arm's counters to `counts` (a, b, c) and a gimbal's to zero.
    pub fn set_encoders(counts: [i16; 3]) -> Self {
        Self {
            currents_ma: [0; 3],
            command: COMMAND_SET_ENCODERS,
            attributes: counts,
        }
    }

    /// Decode the 14 bytes of an output report.
    ///
    /// # Errors
    /// [`ProtocolError::Length`] for any other length.
    pub fn decode(bytes: &[u8]) -> Result<Self, ProtocolError> {
        check_length(bytes)?;
        Ok(Self {
            currents_ma: [field(bytes, 0), field(bytes, 1), field(bytes, 2)],
            command: field(bytes, 3),
            attributes: [field(bytes, 4), field(bytes, 5), field(bytes, 6)],
        })
    }

    pub fn encode(&self, out: &mut [u8; REPORT_LEN]) {
        for (n, c) in self.currents_ma.iter().enumerate() {
            put(out, n, *c);
        }
        put(out, 3, self.command);
        for (n, a) in self.attributes.iter().enumerate() {
            put(out, 4 + n, *a);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn an_input_report_is_seven_little_endian_int16s() {
        // Encoders a..f = 1, -2, 6000, 0, 32767, -32768; info = 1 (docs/devices.md §1).
        let bytes: [u8; 14] = [
            0x01, 0x00, 0xfe, 0xff, 0x70, 0x17, 0x00, 0x00, 0xff, 0x7f, 0x00, 0x80, 0x01, 0x00,
        ];
        let r = EncoderReport::decode(&bytes).unwrap();
        assert_eq!(r.counts, [1, -2, 6000, 0, 32767, -32768]);
        assert!(r.calibration_requested());
        let mut out = [0; REPORT_LEN];
        r.encode(&mut out);
        assert_eq!(out, bytes);
    }

    #[test]
    fn an_output_report_carries_milliamps_then_the_command_and_its_attributes() {
        let mut out = [0; REPORT_LEN];
        CurrentReport::currents([1500, -250, 0]).encode(&mut out);
        assert_eq!(out, [0xdc, 0x05, 0x06, 0xff, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0]);
        CurrentReport::set_encoders([0, 0, 6000]).encode(&mut out);
        assert_eq!(out, [0, 0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 0, 0x70, 0x17]);
        assert_eq!(
            CurrentReport::decode(&out).unwrap(),
            CurrentReport::set_encoders([0, 0, 6000])
        );
    }

    #[test]
    fn reports_of_another_length_are_refused() {
        for n in [0, 13, 15, 64] {
            let bytes = vec![0u8; n];
            assert_eq!(
                EncoderReport::decode(&bytes),
                Err(ProtocolError::Length {
                    got: n,
                    expected: REPORT_LEN
                })
            );
            assert!(CurrentReport::decode(&bytes).is_err());
        }
    }

    proptest! {
        #![proptest_config(crate::protocol::fuzz::config())]

        #[test]
        fn every_fourteen_bytes_decode_and_encode_back_exactly(bytes in prop::array::uniform14(any::<u8>())) {
            let mut out = [0; REPORT_LEN];
            EncoderReport::decode(&bytes).unwrap().encode(&mut out);
            prop_assert_eq!(out, bytes);
            CurrentReport::decode(&bytes).unwrap().encode(&mut out);
            prop_assert_eq!(out, bytes);
        }
    }
}
