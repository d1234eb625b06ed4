//! The candidate effects: physical terms the nominal model (the grid's gravity force F_G(X) and a
//! moving mass m per axis) may be missing. Each adds, to the force the device needs to move as
//! measured, a term linear in its parameters θ, except the time delay, which shifts the command
//! (docs/discrepancy.md gives each one's signature and what it is confounded with):
//!
//! F(t − τ) = F_G(X) + diag(m) Ẍ + Σ θ_j φ_j(X, Ẋ, Ẍ)

use nalgebra::{Matrix3, Vector3};

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
    /// linear in the increment ε: R(δ + ε) F_G ≈ R(δ) F_G + ε × R(δ) F_G. For an arm, whose
    /// links' weights turn and not the handle force, δ is the linear term of [`Sample::tilt`]
    /// scaled as `Fit::turned` (analysis.rs) says: cos|δ| F_G + (sin|δ|/|δ|) Σ δ_i T_i.
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
                out[0] = s.sliding;
                1
            }
            Effect::ViscousDamping => {
                out[0] = s.velocity;
                1
            }
            Effect::GravityTilt => {
                if let Some(columns) = s.tilt {
                    out[..2].copy_from_slice(&columns);
                    return 2;
                }
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

/// For a device whose grid carries an arm: its joints at one sample (smoothed alike, SI).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct JointSample {
    /// q − q̄ (q̄ the log's mean), rad.
    pub offset: Vector3<f64>,
    /// q̇, rad/s, and q̈, rad/s².
    pub rate: Vector3<f64>,
    pub acceleration: Vector3<f64>,
    /// J⁻ᵀ: a joint torque τ needs the handle force J⁻ᵀ τ.
    pub to_handle: Matrix3<f64>,
    /// Each joint's direction of sliding, q̇_j/√(q̇_j² + ω_s²) ([`STICK_RATE`]), smoothed by the
    /// kernel as the command is (see [`Sample::sliding`]).
    pub sliding: Vector3<f64>,
}

/// Below this joint rate a joint's Coulomb friction is smoothed over, rad/s (about
/// [`STICK_SPEED`] at the handle of a 0.1 m link).
pub const STICK_RATE: f64 = 1e-2;

/// The nominal model's own columns for an arm, as handle forces J⁻ᵀ τ: first the joint-space
/// inertia M₀ q̈ (M₀ symmetric: 6 entries); then each joint's Coulomb and viscous friction; then
/// a point mass at the handle, m Ẍ (`handle_acceleration`), whose joint-space inertia m JᵀJ is
/// far from constant or linear in q (the handle itself, a delta's platform); last, the inertia's
/// first order in the joints' offsets δq_k from the log's mean, M(q) = M₀ + Σ_k δq_k M_k (three
/// more symmetric matrices), with the Coriolis and centrifugal torque it implies,
/// Ṁ q̇ − ½ ∂(q̇ᵀ M q̇)/∂q = Σ_k (δq_k M_k q̈ + q̇_k M_k q̇ − ½ (q̇ᵀ M_k q̇) e_k), linear in the same
/// entries. A fit takes the first [`ArmInertia::columns`] of them. Writes [`ARM_COLUMNS`].
/// (Products of the offsets, second order, were tried: the fit then followed its training
/// samples, and a clean PHANToM log's held-out residual grew fivefold.)
pub fn arm_columns(
    j: &JointSample,
    handle_acceleration: &Vector3<f64>,
    out: &mut [Vector3<f64>],
) -> usize {
    const PAIRS: [(usize, usize); 6] = [(0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)];
    // J⁻ᵀ E v, for the symmetric unit matrix E with ones at (a, b) and (b, a): J⁻ᵀ's columns
    // weighted by v.
    let column = |a: usize| j.to_handle.column(a).into_owned();
    let through = |a: usize, b: usize, v: &Vector3<f64>| {
        if a == b {
            column(a) * v[a]
        } else {
            column(a) * v[b] + column(b) * v[a]
        }
    };
    let (offset, rate) = (&j.offset, &j.rate);
    for (n, (a, b)) in PAIRS.into_iter().enumerate() {
        let inertial = through(a, b, &j.acceleration);
        let momentum = through(a, b, rate);
        let quadratic = if a == b {
            rate[a] * rate[a]
        } else {
            2.0 * rate[a] * rate[b]
        };
        out[n] = inertial;
        for k in 0..3 {
            out[ARM_FIRST_ORDER + 6 * k + n] =
                inertial * offset[k] + momentum * rate[k] - column(k) * (0.5 * quadratic);
        }
    }
    for joint in 0..3 {
        out[ARM_FRICTION + 2 * joint] = column(joint) * j.sliding[joint];
        out[ARM_FRICTION + 2 * joint + 1] = column(joint) * j.rate[joint];
    }
    out[ARM_HANDLE_MASS] = *handle_acceleration;
    ARM_COLUMNS
}

/// How many columns [`arm_columns`] writes.
pub const ARM_COLUMNS: usize = 31;
/// Where [`arm_columns`]' friction starts: joint j's Coulomb friction at this + 2j, its viscous
/// friction after it.
pub const ARM_FRICTION: usize = 6;
/// [`arm_columns`]' point mass at the handle.
pub const ARM_HANDLE_MASS: usize = 12;
/// Where [`arm_columns`]' inertia first order in the pose starts (M_k's entries at this + 6k).
pub const ARM_FIRST_ORDER: usize = 13;

/// How an arm's nominal model lets its joint-space inertia vary with the pose, beside the
/// handle's point mass (whose m JᵀJ varies as the kinematics say). `hgcd analyze` chooses by
/// the held-out error ([`crate::discrepancy::analysis::nominal`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ArmInertia {
    /// M₀: a parallel linkage's arms turn about fixed axes, whatever the pose (a delta's), so
    /// only the platform's mass moves its inertia.
    Constant,
    /// M₀ + Σ_k δq_k M_k: a serial arm's links swing about each other (a PHANToM's).
    FirstOrder,
}

impl ArmInertia {
    /// How many of [`arm_columns`]' columns a fit with this inertia takes (the first ones).
    pub fn columns(self) -> usize {
        match self {
            ArmInertia::Constant => ARM_FIRST_ORDER,
            ArmInertia::FirstOrder => ARM_COLUMNS,
        }
    }

    /// Its name in summary.json.
    pub fn name(self) -> &'static str {
        match self {
            ArmInertia::Constant => "constant",
            ArmInertia::FirstOrder => "first_order",
        }
    }
}

/// What the model sees at one sample (smoothed alike, SI).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sample {
    pub position: Vector3<f64>,
    pub velocity: Vector3<f64>,
    pub acceleration: Vector3<f64>,
    /// The direction of sliding, Ẋ/√(|Ẋ|² + v_s²) ([`STICK_SPEED`]), smoothed by the kernel as
    /// the command is: the command that balances Coulomb friction switches with the velocity,
    /// and smoothing the switch is not switching the smoothed velocity.
    pub sliding: Vector3<f64>,
    /// The nominal model's gravity force F_G(X), N.
    pub gravity: Vector3<f64>,
    /// The grid's v_G and g.
    pub up: Vector3<f64>,
    pub g: f64,
    /// The arm's joints, for a device whose grid carries an arm.
    pub joint: Option<JointSample>,
    /// For an arm model: ∂F_G/∂δ along the two directions across v_G of [`across`], the
    /// gravity force's change as the arm's gravity turns (its links' weights turn, not the
    /// handle force); None for a field that turns whole.
    pub tilt: Option<[Vector3<f64>; 2]>,
}

pub use crate::fit::across;

/// The symmetric matrix with entries (xx, yy, zz, xy, xz, yz), the order of the arm's inertia
/// columns.
pub fn symmetric(e: &[f64]) -> Matrix3<f64> {
    Matrix3::new(e[0], e[3], e[4], e[3], e[1], e[5], e[4], e[5], e[2])
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The arm's columns, weighted by M(q)'s entries and the joints' friction, give J⁻ᵀ times
    /// the Euler–Lagrange torque d/dt(M(q) q̇) − ½ ∂(q̇ᵀ M(q) q̇)/∂q of M(q) = M₀ + Σ_k δq_k M_k
    /// (worked out here by finite differences along q(t) = q + q̇ t + q̈ t²/2) plus the friction,
    /// and a point mass at the handle its m Ẍ.
    #[test]
    fn the_arm_columns_are_the_dynamics_of_a_first_order_inertia_and_a_handle_mass() {
        let entries: [[f64; 6]; 4] = [
            [4e-3, 3e-3, 2e-3, 1e-4, -2e-4, 5e-5],
            [3e-4, -1e-4, 2e-4, 4e-4, 1e-4, -3e-4],
            [-2e-4, 5e-4, 1e-4, -1e-4, 3e-4, 2e-4],
            [1e-4, 2e-4, -4e-4, 2e-4, -1e-4, 1e-4],
        ];
        let inertia = |q: &Vector3<f64>| {
            (0..3).fold(symmetric(&entries[0]), |m, k| {
                m + symmetric(&entries[k + 1]) * q[k]
            })
        };
        let (q, rate, acceleration) = (
            Vector3::new(0.2, -0.1, 0.3),
            Vector3::new(1.5, -2.0, 0.7),
            Vector3::new(-30.0, 12.0, 45.0),
        );
        let h = 1e-5;
        let at = |t: f64| {
            (
                q + rate * t + acceleration * (t * t / 2.0),
                rate + acceleration * t,
            )
        };
        let momentum = |t: f64| {
            let (q, rate) = at(t);
            inertia(&q) * rate
        };
        let energy = |q: &Vector3<f64>| 0.5 * rate.dot(&(inertia(q) * rate));
        let gradient = Vector3::from_fn(|k, _| {
            let dq = Vector3::from_fn(|i, _| if i == k { h } else { 0.0 });
            (energy(&(q + dq)) - energy(&(q - dq))) / (2.0 * h)
        });
        let lagrange = (momentum(h) - momentum(-h)) / (2.0 * h) - gradient;

        // Each joint's Coulomb (along its direction of sliding) and viscous friction, interleaved
        // as the columns are; and a J⁻ᵀ that is not symmetric, so rows and columns cannot mix.
        let (coulomb, viscous) = ([0.01, 0.02, 0.03], [1e-3, 2e-3, 3e-3]);
        let sliding = Vector3::new(0.9, -1.0, 0.5);
        let to_handle = Matrix3::new(3.0, 1.0, -2.0, 0.5, 4.0, 1.5, -1.0, 2.5, 5.0);
        let friction = Vector3::from_fn(|j, _| coulomb[j] * sliding[j] + viscous[j] * rate[j]);
        // A point mass at the handle, accelerated along its own Ẍ.
        let (handle_mass, handle_acceleration) = (0.05, Vector3::new(0.4, -1.2, 0.9));
        let truth = to_handle * (lagrange + friction) + handle_acceleration * handle_mass;

        let sample = JointSample {
            offset: q,
            rate,
            acceleration,
            to_handle,
            sliding,
        };
        let mut columns = [Vector3::zeros(); ARM_COLUMNS];
        assert_eq!(
            arm_columns(&sample, &handle_acceleration, &mut columns),
            ARM_COLUMNS
        );
        let parameters = entries[0]
            .into_iter()
            .chain((0..3).flat_map(|j| [coulomb[j], viscous[j]]))
            .chain([handle_mass])
            .chain(entries[1..].iter().flatten().copied());
        let modelled: Vector3<f64> = parameters
            .zip(&columns)
            .map(|(theta, column)| column * theta)
            .sum();
        assert!(
            (modelled - truth).norm() < 1e-8 * truth.norm(),
            "{modelled} against {truth}"
        );
        // The velocity-product part is there: the inertia alone leaves it out.
        let inertia_alone = inertia(&q) * acceleration;
        assert!((inertia_alone - lagrange).norm() > 1e-3 * lagrange.norm());
    }
}
