//! Which device a grid belongs to. A device that gave its device-info report
//! (`docs/hid-protocol.md` §5a) is known by its model and serial number, whatever it is reached
//! through: its grid is `<model>-<serial>.toml`, so two units behind sockets of the same file
//! name get two grids. A device that gave none is known by the spec it was opened with, as before
//! device-info existed.

use super::{DeviceRecord, GridFile, UnitRecord};
use crate::config::{id_part, DeviceSpec};
use crate::protocol::DeviceInfo;

/// A device as hgcd opened it: the spec and what the device said about itself, if anything.
#[derive(Clone, Debug, PartialEq)]
pub struct DeviceIdentity {
    /// The spec the device was opened with (a HID device's serial number filled in).
    pub spec: DeviceSpec,
    /// Its device-info report; None for a device that did not give one.
    pub info: Option<DeviceInfo>,
}

impl DeviceIdentity {
    /// The device opened as `spec` that described itself as `info`. A HID device whose report
    /// gives no serial number is known by its USB serial number, when it has one.
    pub fn new(spec: DeviceSpec, info: Option<DeviceInfo>) -> Self {
        let info = info.map(|mut info| {
            if let DeviceSpec::Hid {
                serial: Some(usb), ..
            } = &spec
            {
                if info.serial.is_empty() {
                    info.serial = usb.clone();
                }
            }
            info
        });
        Self { spec, info }
    }

    /// A device known by its spec alone.
    pub fn of_spec(spec: DeviceSpec) -> Self {
        Self { spec, info: None }
    }

    /// The id the device's grid is named after (`<state_dir>/<id>.toml`): `model-serial` (or
    /// `model` for a device without a serial number) from the device-info report, else the
    /// spec's id ([`DeviceSpec::device_id`]).
    pub fn grid_id(&self) -> String {
        match &self.info {
            Some(info) if info.serial.is_empty() => id_part(&info.model),
            Some(info) => format!("{}-{}", id_part(&info.model), id_part(&info.serial)),
            None => self.spec.device_id(),
        }
    }

    /// The unit, as its device-info report names it.
    pub fn unit(&self) -> Option<UnitRecord> {
        self.info.as_ref().map(|info| UnitRecord {
            model: info.model.clone(),
            serial: info.serial.clone(),
        })
    }

    /// Record this device in `file` (its `[device]` table), replacing what was there.
    pub fn stamp(&self, file: &mut GridFile) {
        file.device = Some(DeviceRecord {
            id: self.grid_id(),
            spec: Some(self.spec.to_string()),
            model: self.info.as_ref().map(|info| info.model.clone()),
            serial: self.info.as_ref().map(|info| info.serial.clone()),
        });
    }
}

impl std::fmt::Display for DeviceIdentity {
    /// The spec, and the unit when the device named itself.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.unit() {
            Some(unit) => write!(f, "{} ({unit})", self.spec),
            None => write!(f, "{}", self.spec),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    pub(crate) fn info(model: &str, serial: &str) -> DeviceInfo {
        DeviceInfo {
            model: model.into(),
            serial: serial.into(),
            workspace_centre: Vector3::new(0.0, 0.15, 0.0),
            workspace_half_extents: Vector3::repeat(0.06),
            max_force: 3.0,
            rate_hz: 1000.0,
            lockstep: true,
        }
    }

    #[test]
    fn grids_are_named_after_the_unit_when_it_names_itself() {
        let spec: DeviceSpec = "socket:/run/a/dev.sock".parse().unwrap();
        let bare = DeviceIdentity::of_spec(spec.clone());
        assert_eq!(bare.grid_id(), "socket-dev_sock");
        let a = DeviceIdentity {
            spec: spec.clone(),
            info: Some(info("PHANToM-like 3", "SN/7")),
        };
        assert_eq!(a.grid_id(), "PHANToM-like_3-SN_7");
        // Another unit behind a socket of the same file name has another grid.
        let b = DeviceIdentity {
            spec: "socket:/run/b/dev.sock".parse().unwrap(),
            info: Some(info("PHANToM-like 3", "SN/8")),
        };
        assert_ne!(a.grid_id(), b.grid_id());
        // The emulated firmware without a serial keeps the name grids of `sim:` always had.
        let sim = DeviceIdentity {
            spec: "sim:point-mass".parse().unwrap(),
            info: Some(info("sim-point-mass", "")),
        };
        assert_eq!(sim.grid_id(), "sim-point-mass");
        // A HID device without a serial in its report: the USB serial number tells units apart.
        let hid = DeviceIdentity::new(
            "hid:1234:abcd:SN 7".parse().unwrap(),
            Some(info("Delta", "")),
        );
        assert_eq!(hid.grid_id(), "Delta-SN_7");
        assert_eq!(hid.unit().unwrap().serial, "SN 7");
        assert_eq!(
            a.to_string(),
            "socket:/run/a/dev.sock (PHANToM-like 3 serial SN/7)"
        );
    }
}
