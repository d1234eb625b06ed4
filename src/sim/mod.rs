//! Simulated devices, in one place: the physics ([`Plant`], [`PointMass`]), the encoders
//! ([`Encoder`]), the emulated v1 firmware around them ([`SimDevice`]) and the device side of the
//! socket transport ([`socket::serve`], behind `hgcd sim-device`). The host reaches an in-process
//! simulated device through `transport::sim`, an external one through `transport::socket`.
//!
//! A plant integrates the end-effector dynamics under the actuator force the firmware gives it;
//! measurement effects (encoder quantisation, noise) are applied by [`Encoder`] when a report is made.

mod encoder;
mod firmware;
mod point_mass;
pub mod socket;

pub use encoder::Encoder;
pub use firmware::SimDevice;
pub use point_mass::PointMass;

use nalgebra::Vector3;

/// The physics of a simulated device.
pub trait Plant: Send {
    /// Integrate for `dt` seconds under the actuator force `force` (N, already limited).
    fn step(&mut self, force: &Vector3<f64>, dt: f64);
    /// True end-effector position, m.
    fn position(&self) -> Vector3<f64>;
    /// True end-effector velocity, m/s.
    fn velocity(&self) -> Vector3<f64>;
    /// The box the mechanical stops allow, m: (smallest corner, largest corner).
    fn workspace(&self) -> (Vector3<f64>, Vector3<f64>);
    /// The actuator force that holds the handle still where it is now, payload included, N: the
    /// plant's own analytic answer to what calibration measures (ground truth for tests).
    fn holding_force(&self) -> Vector3<f64>;
}
