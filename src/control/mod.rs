//! Controllers: tick functions from device state to force. Calibration and compensation are
//! controllers too, so each is unit-testable without threads or devices.

pub mod calibration;
pub mod compensation;
pub mod pd;

use nalgebra::Vector3;

use crate::protocol::Status;

/// The minimum-jerk profile at progress τ (clamped to [0, 1]): the share of the move covered,
/// τ³ (10 − 15τ + 6τ²), and its rate d/dτ, 30 τ² (1 − τ)². The calibration's moves and
/// strokes, the validation's probe and the excitation's moves to its holds all follow it.
pub fn minimum_jerk(tau: f64) -> (f64, f64) {
    let t = tau.clamp(0.0, 1.0);
    (
        t * t * t * (10.0 - 15.0 * t + 6.0 * t * t),
        30.0 * t * t * (1.0 - t) * (1.0 - t),
    )
}

/// What the servo loop knows about the device at one tick. SI units throughout.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DeviceState {
    /// Device time since the first report, s (from the report's timestamp).
    pub time: f64,
    /// When the report arrived on the transport's clock, s: monotonic host time on hardware, the
    /// device clock in virtual time. Lets a controller notice a device clock that stops.
    pub host_time: f64,
    /// End-effector position, m.
    pub position: Vector3<f64>,
    /// FOAW velocity estimate, m/s.
    pub velocity: Vector3<f64>,
    /// Status flags of the latest input report.
    pub status: Status,
    /// Ticks since the loop started.
    pub tick: u64,
}

/// A controller's answer for one tick.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ControlOutput {
    /// Force to render on the end effector, N (the safety layer limits it).
    pub force: Vector3<f64>,
    /// The controller has finished; the loop ends after writing this tick's force.
    pub done: bool,
}

impl ControlOutput {
    pub fn force(force: Vector3<f64>) -> Self {
        Self { force, done: false }
    }
    pub fn done(force: Vector3<f64>) -> Self {
        Self { force, done: true }
    }
}

/// A tick function run by the servo loop, once per input report (about 1 kHz), on the servo
/// thread. The first call sees the first report. A controller that returns
/// [`ControlOutput::done`] is not called again. None of the methods may allocate, lock, block,
/// log synchronously or read a clock: time comes in [`DeviceState`].
///
/// Per tick the loop calls `before_tick` (mailbox work: take commands from outside), `tick`
/// (state to force, the critical step) and, once the safety layer has limited that force,
/// `after_tick` with the force the output report carries (publish what was done).
pub trait Controller: Send {
    fn before_tick(&mut self, _state: &DeviceState) {}
    fn tick(&mut self, state: &DeviceState) -> ControlOutput;
    fn after_tick(&mut self, _state: &DeviceState, _sent: &Vector3<f64>) {}
}

/// Renders no force at all.
#[derive(Clone, Copy, Debug, Default)]
pub struct ZeroForce;

impl Controller for ZeroForce {
    fn tick(&mut self, _: &DeviceState) -> ControlOutput {
        ControlOutput::force(Vector3::zeros())
    }
}
