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
    /// The position the device's own sensors report with the handle displaced by `noise` (m)
    /// from where it is: quantised as its encoders quantise (Cartesian for the point mass, joint
    /// angles then forward kinematics for a linkage).
    fn sensed_position(&self, noise: &Vector3<f64>) -> Vector3<f64>;
    /// Unit "up" of the simulated world in the device frame: opposite to gravity.
    fn up(&self) -> Vector3<f64>;
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
