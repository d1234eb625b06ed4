//! The candidate effects: physical terms the nominal model (the grid's gravity force F_G(X) and a
//! moving mass m per axis) may be missing. Each adds, to the force the device needs to move as
//! measured, a term linear in its parameters θ, except the time delay, which shifts the command
//! (docs/discrepancy.md gives each one's signature and what it is confounded with):
//!
//! F(t − τ) = F_G(X) + diag(m) Ẍ + Σ θ_j φ_j(X, Ẋ, Ẍ)

use nalgebra::Vector3;

/// Below this speed the handle counts as stuck, m/s: Coulomb friction then holds any force up
/// to f_c (the velocity estimate's noise is some 0.1 mm/s), and above it its direction is
/// smoothed over this speed.
pub const STICK_SPEED: f64 = 1e-3;

/// A physical effect, by the name `summary.json` gives it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Effect {
    /// The model explains the log: nothing is named.
    None,
    /// A mass m_p added at the handle: weight m_p g along −v_G and inertia. θ = m_p (kg).
    Payload,
    /// Coulomb friction at the handle, f_c against the motion. θ = f_c (N).
    CoulombFriction,
    /// Viscous damping b at the handle, b Ẋ against the motion. θ = b (N·s/m).
    ViscousDamping,
    /// Gravity turned by a rotation δ ⊥ v_G (the device tilted after calibration): the gravity
    /// force R(δ) F_G. δ (rad, two components across v_G) is found by Gauss–Newton steps, each
    /// linear in the increment ε: R(δ + ε) F_G ≈ R(δ) F_G + ε × R(δ) F_G.
    GravityTilt,
    /// A spring k (X − X_0) (a cable, a hose). θ = (k, −k X_0) (N/m, N).
    Spring,
    /// The actuators render the command τ late. θ = τ (s), found by search.
    TimeDelay,
}

impl Effect {
    /// Every candidate, simplest first.
    pub const CANDIDATES: [Effect; 6] = [
        Effect::Payload,
        Effect::CoulombFriction,
        Effect::ViscousDamping,
        Effect::TimeDelay,
        Effect::GravityTilt,
        Effect::Spring,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Effect::None => "none",
            Effect::Payload => "payload",
            Effect::CoulombFriction => "coulomb_friction",
            Effect::ViscousDamping => "viscous_damping",
            Effect::GravityTilt => "gravity_tilt",
            Effect::Spring => "spring",
            Effect::TimeDelay => "time_delay",
        }
    }

    /// Parameters it adds to the nominal model.
    pub fn parameters(self) -> usize {
        match self {
            Effect::None => 0,
            Effect::Payload | Effect::CoulombFriction | Effect::ViscousDamping => 1,
            Effect::TimeDelay => 1,
            Effect::GravityTilt => 2,
            Effect::Spring => 4,
        }
    }

    /// Of those, the ones its linear term carries ([`Effect::columns`]).
    pub fn linear_parameters(self) -> usize {
        match self {
            Effect::TimeDelay => 0,
            other => other.parameters(),
        }
    }

    /// The columns φ_j of its linear term at one sample, into `out`; how many. None for the time
    /// delay, which is not linear.
    pub fn columns(self, s: &Sample, out: &mut [Vector3<f64>; 4]) -> usize {
        match self {
            Effect::None | Effect::TimeDelay => 0,
            Effect::Payload => {
                out[0] = s.up * s.g + s.acceleration;
                1
            }
            Effect::CoulombFriction => {
                let v = s.velocity;
                out[0] = v / (v.norm_squared() + STICK_SPEED.powi(2)).sqrt();
                1
            }
            Effect::ViscousDamping => {
                out[0] = s.velocity;
                1
            }
            Effect::GravityTilt => {
                let (e1, e2) = across(&s.up);
                out[0] = e1.cross(&s.gravity);
                out[1] = e2.cross(&s.gravity);
                2
            }
            Effect::Spring => {
                out[0] = s.position;
                out[1] = Vector3::x();
                out[2] = Vector3::y();
                out[3] = Vector3::z();
                4
            }
        }
    }
}

/// What the model sees at one sample (smoothed alike, SI).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sample {
    pub position: Vector3<f64>,
    pub velocity: Vector3<f64>,
    pub acceleration: Vector3<f64>,
    /// The nominal model's gravity force F_G(X), N.
    pub gravity: Vector3<f64>,
    /// The grid's v_G and g.
    pub up: Vector3<f64>,
    pub g: f64,
}

pub use crate::fit::across;
