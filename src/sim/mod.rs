//! Simulated devices, in one place: the physics ([`Plant`]: [`PointMass`], and the linkages of
//! [`linkage`]: [`phantom`], [`delta`], [`woodenhaptics`]), the position measurement
//! ([`Encoder`]), the emulated firmware around them ([`SimDevice`]: v1, or the WoodenHaptics
//! protocol for `sim:woodenhaptics`) and the device side of the socket transport ([`socket::serve`],
//! behind `hgcd sim-device`). The host reaches an in-process simulated device through
//! `transport::sim`, an external one through `transport::socket`.
//!
//! A plant integrates its dynamics under the actuator force the firmware gives it and says what
//! its own sensors read ([`Plant::sensed_position`]); [`Encoder`] adds the measurement noise when a
//! report is made.

pub mod delta;
mod encoder;
mod firmware;
pub mod linkage;
pub mod phantom;
mod point_mass;
pub mod socket;
pub mod woodenhaptics;

pub use encoder::Encoder;
pub use firmware::SimDevice;
pub use point_mass::PointMass;

use std::sync::atomic::{AtomicU64, Ordering};

use nalgebra::Vector3;

use crate::grid::GridError;

/// The physics of a simulated device.
pub trait Plant: Send {
    /// Integrate for `dt` seconds under the actuator force `force` (N, already limited).
    fn step(&mut self, force: &Vector3<f64>, dt: f64);
    /// True end-effector position, m.
    fn position(&self) -> Vector3<f64>;
    /// True end-effector velocity, m/s.
    fn velocity(&self) -> Vector3<f64>;
    /// A box holding every position the mechanical stops allow, m: (smallest corner, largest).
    fn workspace(&self) -> (Vector3<f64>, Vector3<f64>);
    /// The actuator force that holds the handle still where it is now, payload included, N: the
    /// plant's own analytic answer to what calibration measures (ground truth for tests).
    fn holding_force(&self) -> Vector3<f64>;
    /// The moving mass along x, y and z where the handle is now, kg: the force along an axis
    /// over the acceleration it gives along it from rest, the other axes free (1 / (J H⁻¹ Jᵀ)_aa
    /// on a linkage, rotors and payload included): what calibration's pulses time (ground truth
    /// for tests).
    fn moving_mass_per_axis(&self) -> Vector3<f64>;
    /// The position the device's own sensors report with the handle displaced by `noise` (m)
    /// from where it is: quantised as its encoders quantise (Cartesian for the point mass, joint
    /// angles then forward kinematics for a linkage).
    fn sensed_position(&self, noise: &Vector3<f64>) -> Vector3<f64>;
    /// Unit "up" of the simulated world in the device frame: opposite to gravity.
    fn up(&self) -> Vector3<f64>;
    /// Every time the handle met a mechanical stop or an obstacle, and how fast (ground truth
    /// for tests: no contact faster than exploration's bound).
    fn contacts(&self) -> &ContactLog;
    /// From now on the handle carries `payload_kg` (the `sim.probe_mass_kg` of a changed
    /// config) and gravity pulls against the unit `up` (a tilted base), with the same g.
    fn set_world(&mut self, payload_kg: f64, up: &Vector3<f64>);
}

/// A change of a running simulated device's world: the payload on its handle and the direction
/// of gravity. Set from another thread (`hgcd run` on SIGHUP, a test) and taken by the device
/// before its next report, without a lock: a sequence counter, odd while a change is written.
#[derive(Debug, Default)]
pub struct LiveWorld {
    version: AtomicU64,
    payload_kg: AtomicU64,
    up: [AtomicU64; 3],
}

impl LiveWorld {
    /// The handle carries `payload_kg` from now on, and gravity pulls against `up` (normalised;
    /// a zero or non-finite `up`, or a payload that is not finite, changes nothing).
    pub fn set(&self, payload_kg: f64, up: Vector3<f64>) {
        let norm = up.norm();
        if !(payload_kg.is_finite() && norm.is_finite() && norm > 0.0) {
            return;
        }
        let up = up / norm;
        // Writers take turns: whoever makes the counter odd writes.
        loop {
            let v = self.version.load(Ordering::Acquire);
            if v % 2 == 0
                && self
                    .version
                    .compare_exchange(v, v + 1, Ordering::AcqRel, Ordering::Relaxed)
                    .is_ok()
            {
                break;
            }
            std::hint::spin_loop();
        }
        self.payload_kg
            .store(payload_kg.to_bits(), Ordering::Release);
        for (cell, c) in self.up.iter().zip(up.iter()) {
            cell.store(c.to_bits(), Ordering::Release);
        }
        self.version.fetch_add(1, Ordering::Release);
    }

    /// The change made since the version `seen` (which it updates), if a whole one is there.
    pub fn changed(&self, seen: &mut u64) -> Option<(f64, Vector3<f64>)> {
        let before = self.version.load(Ordering::Acquire);
        if before == *seen || before % 2 == 1 {
            return None;
        }
        let payload = f64::from_bits(self.payload_kg.load(Ordering::Acquire));
        let up = Vector3::from_fn(|i, _| f64::from_bits(self.up[i].load(Ordering::Acquire)));
        if self.version.load(Ordering::Acquire) != before {
            return None;
        }
        *seen = before;
        Some((payload, up))
    }
}

/// One contact: the handle met a mechanical stop or an obstacle it was not touching before.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Contact {
    /// Plant time since it was built, s.
    pub time: f64,
    /// Where the handle stopped, m.
    pub position: Vector3<f64>,
    /// The handle's speed into the stop, m/s: the part of its velocity just before that the
    /// stop absorbed (along a stop it met at an angle, the handle slides on with the rest).
    pub speed: f64,
}

/// A plant's contacts, oldest first: room for [`ContactLog::ROOM`] is made when the plant is
/// built (the plant steps on the servo thread, which must not allocate); later ones are only
/// counted, with the fastest of them kept.
#[derive(Clone, Debug)]
pub struct ContactLog {
    contacts: Vec<Contact>,
    /// Contacts beyond the room, and the fastest of them, m/s.
    missed: u64,
    fastest_missed: f64,
    /// Plant time, s.
    time: f64,
}

impl Default for ContactLog {
    fn default() -> Self {
        Self {
            contacts: Vec::with_capacity(Self::ROOM),
            missed: 0,
            fastest_missed: 0.0,
            time: 0.0,
        }
    }
}

impl ContactLog {
    /// Contacts kept in full.
    pub const ROOM: usize = 4096;

    /// Advance the plant's clock by a step of `dt` s.
    pub(crate) fn tick(&mut self, dt: f64) {
        self.time += dt;
    }

    /// The handle met a stop at `position` (m) at `speed` (m/s).
    pub(crate) fn record(&mut self, position: Vector3<f64>, speed: f64) {
        if self.contacts.len() < Self::ROOM {
            self.contacts.push(Contact {
                time: self.time,
                position,
                speed,
            });
        } else {
            self.missed += 1;
            self.fastest_missed = self.fastest_missed.max(speed);
        }
    }

    /// The contacts kept, oldest first.
    pub fn contacts(&self) -> &[Contact] {
        &self.contacts
    }

    /// How many contacts there were in all.
    pub fn count(&self) -> u64 {
        self.contacts.len() as u64 + self.missed
    }

    /// The fastest contact of all, m/s (0 without any).
    pub fn fastest(&self) -> f64 {
        self.contacts
            .iter()
            .map(|c| c.speed)
            .fold(self.fastest_missed, f64::max)
    }
}

/// Why a simulated device could not be built from its config.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    #[error(transparent)]
    Grid(#[from] GridError),
    #[error(transparent)]
    Profile(#[from] crate::profile::ProfileError),
    #[error(
        "sim:woodenhaptics needs a WoodenHaptics-protocol profile with [kinematics] and [bodies]; \
         device profile `{profile}` has none (set device.profile, e.g. woodenhaptics_v2015)"
    )]
    NoArm { profile: String },
    #[error(
        "{key} acts along the device's axes, in protocol v1's firmware: sim:woodenhaptics speaks \
         joint currents and has none (docs/simulated-devices.md, Config keys); leave it unset"
    )]
    CartesianOnly { key: &'static str },
    #[error("unknown simulated model `{model}`; known: {}", crate::config::SIM_MODELS.join(", "))]
    UnknownModel { model: String },
    #[error(
        "sim.start_position_mm {position_mm:?} is out of reach of sim:{model}: give a point inside its \
         joint limits (the origin is its home pose)"
    )]
    Unreachable {
        model: &'static str,
        position_mm: [f64; 3],
    },
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_live_change_is_taken_once_and_whole() {
        let world = LiveWorld::default();
        let mut seen = 0;
        assert_eq!(world.changed(&mut seen), None);
        world.set(0.03, Vector3::new(0.0, 0.0, 2.0));
        assert_eq!(world.changed(&mut seen), Some((0.03, Vector3::z())));
        assert_eq!(world.changed(&mut seen), None);
        world.set(f64::NAN, Vector3::z());
        world.set(0.01, Vector3::zeros());
        assert_eq!(world.changed(&mut seen), None);
    }

    #[test]
    fn the_contact_log_keeps_its_room_then_counts_and_keeps_the_fastest() {
        let mut log = ContactLog::default();
        assert_eq!((log.count(), log.fastest()), (0, 0.0));
        for n in 0..ContactLog::ROOM {
            log.tick(1e-3);
            log.record(Vector3::zeros(), 0.001 * (n % 10) as f64);
        }
        log.record(Vector3::x(), 0.5);
        log.record(Vector3::y(), 0.1);
        assert_eq!(log.contacts().len(), ContactLog::ROOM);
        assert_eq!(log.count(), ContactLog::ROOM as u64 + 2);
        assert_eq!(log.fastest(), 0.5);
        assert!((log.contacts()[1].time - 2e-3).abs() < 1e-12);
    }
}
