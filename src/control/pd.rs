//! Feedback-linearised PD hold (paper Eqs. 3–5): F = k_P (X_D − X) − k_D V̂ + F_G(X), with
//! k_D = α M and k_P = β M, so that Ẍ = −α Ẋ + β (X_D − X) when M is right. The law itself is
//! [`LinearisedGains::pd_force`]; every controller that holds or moves the handle (the holds here,
//! the calibration's moves and holds of Eq. 10) calls it.

use nalgebra::Vector3;

use super::{ControlOutput, Controller, DeviceState};
use crate::grid::MassGrid;

/// α and β of the linearised closed loop Ẍ = −α Ẋ + β (X_D − X), chosen from a 10–90 % rise
/// time and a damping ratio ζ: β = ω_n², α = 2 ζ ω_n.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LinearisedGains {
    pub alpha: f64,
    pub beta: f64,
}

impl LinearisedGains {
    /// Gains whose unit step response rises from 10 % to 90 % in `rise_time` s with damping `zeta`.
    pub fn from_rise_time(rise_time: f64, zeta: f64) -> Self {
        let omega = normalised_rise_time(zeta) / rise_time;
        Self {
            alpha: 2.0 * zeta * omega,
            beta: omega * omega,
        }
    }

    /// k_P = β M, N/m.
    pub fn stiffness(&self, mass: f64) -> f64 {
        self.beta * mass
    }

    /// k_D = α M, N·s/m.
    pub fn damping(&self, mass: f64) -> f64 {
        self.alpha * mass
    }

    /// The feedback-linearised PD law, N: F = k_P (X_D − X) − k_D V̂ + F_G, with k_P and k_D built
    /// on `mass` (the mass the loop is linearised for) and `gravity` the gravity term F_G (M g v_G,
    /// or a grid's M(X) g v_G).
    pub fn pd_force(
        &self,
        mass: f64,
        set_point: &Vector3<f64>,
        s: &DeviceState,
        gravity: &Vector3<f64>,
    ) -> Vector3<f64> {
        (set_point - s.position) * self.stiffness(mass) - s.velocity * self.damping(mass) + gravity
    }
}

/// Per-axis PD gains built on measured moving masses: F = K∘(X_D − X) − C∘V̂ + F_ff, with K and
/// C diagonal (one entry per axis of the device frame). What calibration holds the handle with.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AxisGains {
    /// N/m per axis.
    pub stiffness: Vector3<f64>,
    /// N·s/m per axis.
    pub damping: Vector3<f64>,
}

impl AxisGains {
    /// Gains that give each axis of a moving mass `inertia` (kg per axis) the natural frequency
    /// of `base` (β = ω²) or more, enough that a friction band of `friction` (N, half-width per
    /// axis) spans at most `friction_offset` m of hold offset, at most `max_omega` rad/s; damping
    /// ratio ζ = α / (2ω) of `base`. The hold is then feedback-linearised (Eqs. 4–5) on the
    /// measured moving mass, and stiffer where friction would otherwise leave it far off.
    pub fn from_measurement(
        base: &LinearisedGains,
        inertia: &Vector3<f64>,
        friction: &Vector3<f64>,
        friction_offset: f64,
        max_omega: f64,
    ) -> Self {
        let omega_0 = base.beta.sqrt();
        let zeta = base.alpha / (2.0 * omega_0);
        let mut gains = Self {
            stiffness: Vector3::zeros(),
            damping: Vector3::zeros(),
        };
        for a in 0..3 {
            let m = inertia[a];
            let omega = omega_0
                .max((friction[a] / (friction_offset * m)).sqrt())
                .min(max_omega.max(omega_0));
            gains.stiffness[a] = m * omega * omega;
            gains.damping[a] = 2.0 * zeta * omega * m;
        }
        gains
    }

    /// These gains scaled by `factor` (a back-off).
    pub fn scaled(&self, factor: f64) -> Self {
        Self {
            stiffness: self.stiffness * factor,
            damping: self.damping * factor,
        }
    }

    /// The slowest axis's natural frequency for moving masses `inertia`, rad/s.
    pub fn slowest_omega(&self, inertia: &Vector3<f64>) -> f64 {
        (0..3)
            .map(|a| (self.stiffness[a] / inertia[a]).sqrt())
            .fold(f64::INFINITY, f64::min)
    }

    /// F = K∘(X_D − X) − C∘V̂ + F_ff, N.
    pub fn pd_force(
        &self,
        set_point: &Vector3<f64>,
        s: &DeviceState,
        feedforward: &Vector3<f64>,
    ) -> Vector3<f64> {
        (set_point - s.position).component_mul(&self.stiffness)
            - s.velocity.component_mul(&self.damping)
            + feedforward
    }
}

/// 10–90 % rise time of ẍ = −2ζẋ − x + 1 (ω_n = 1) from rest, found by integrating the step
/// response (exact for any ζ > 0, unlike the textbook approximations).
fn normalised_rise_time(zeta: f64) -> f64 {
    let dt = 1e-4;
    let (mut x, mut v, mut t) = (0.0f64, 0.0f64, 0.0f64);
    let mut t10 = None;
    while t < 1e4 {
        let a = 1.0 - x - 2.0 * zeta * v;
        v += a * dt;
        x += v * dt;
        t += dt;
        if t10.is_none() && x >= 0.1 {
            t10 = Some(t);
        }
        if x >= 0.9 {
            return t - t10.unwrap_or(0.0);
        }
    }
    t
}

/// Holds the end effector at a set point with a feedback-linearised PD and a gravity term taken
/// from a mass grid (exact when the grid is the plant's truth).
#[derive(Clone, Debug)]
pub struct PdHold {
    pub set_point: Vector3<f64>,
    pub gains: LinearisedGains,
    pub field: MassGrid,
}

impl Controller for PdHold {
    fn tick(&mut self, s: &DeviceState) -> ControlOutput {
        ControlOutput::force(self.gains.pd_force(
            self.field.mass_at(&s.position),
            &self.set_point,
            s,
            &self.field.gravity_force(&s.position),
        ))
    }
}

/// A PD hold at one point with a constant feedforward force: what the calibration leaves behind
/// at its last vertex (its gains and the holding force it measured there) until the daemon
/// switches to the new grid.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PointHold {
    pub set_point: Vector3<f64>,
    /// The holding force, N.
    pub force: Vector3<f64>,
    pub gains: AxisGains,
}

impl PointHold {
    pub fn force(&self, s: &DeviceState) -> Vector3<f64> {
        self.gains.pd_force(&self.set_point, s, &self.force)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn critically_damped_rise_time_matches_the_closed_form() {
        // For ζ = 1 the 10–90 % rise time is 3.3579/ω_n (solve (1+t)e^{−t} = 0.9 and 0.1).
        assert!((normalised_rise_time(1.0) - 3.3579).abs() < 1e-3);
        let g = LinearisedGains::from_rise_time(0.1, 1.0);
        assert!((g.beta.sqrt() - 33.579).abs() < 0.02);
        assert!((g.alpha - 2.0 * g.beta.sqrt()).abs() < 1e-9);
    }

    #[test]
    fn the_pd_law_pulls_with_beta_m_damps_with_alpha_m_and_adds_the_gravity_term() {
        let gains = LinearisedGains {
            alpha: 20.0,
            beta: 100.0,
        };
        let s = DeviceState {
            time: 0.0,
            host_time: 0.0,
            position: Vector3::new(0.01, 0.0, 0.0),
            velocity: Vector3::new(0.0, 0.2, 0.0),
            status: Default::default(),
            tick: 0,
        };
        let f = gains.pd_force(0.5, &Vector3::zeros(), &s, &Vector3::new(0.0, 0.0, 4.9));
        // k_P = 50 N/m pulls 10 mm back (−0.5 N), k_D = 10 N·s/m resists 0.2 m/s (−2 N).
        assert!((f - Vector3::new(-0.5, -2.0, 4.9)).norm() < 1e-12, "{f}");
    }

    #[test]
    fn axis_gains_follow_the_moving_mass_and_stiffen_against_friction() {
        let base = LinearisedGains::from_rise_time(0.1, 1.0);
        let omega = base.beta.sqrt();
        // Without friction: k = β m, c = α m per axis (the paper's law on the measured mass).
        let m = Vector3::new(0.005, 0.12, 0.5);
        let g = AxisGains::from_measurement(&base, &m, &Vector3::zeros(), 2e-4, 250.0);
        assert!((g.stiffness - m * base.beta).norm() < 1e-9);
        assert!((g.damping - m * base.alpha).norm() < 1e-9);
        assert!((g.slowest_omega(&m) - omega).abs() < 1e-9);
        // 0.1 N of friction on 0.12 kg: ω = √(0.1 / (0.2 mm × 0.12 kg)) = 64.5 rad/s, so the
        // band spans 0.2 mm of offset; on 5 g the cap of 250 rad/s holds; ζ stays 1.
        let f = Vector3::repeat(0.1);
        let g = AxisGains::from_measurement(&base, &m, &f, 2e-4, 250.0);
        assert!((f.y / g.stiffness.y - 2e-4).abs() < 1e-12);
        assert!((g.stiffness.x - 0.005 * 250.0 * 250.0).abs() < 1e-9);
        assert!(
            (g.stiffness.z - 0.5 * base.beta).abs() < 1e-9,
            "heavy enough already"
        );
        for a in 0..3 {
            let zeta = g.damping[a] / (2.0 * (g.stiffness[a] * m[a]).sqrt());
            assert!((zeta - 1.0).abs() < 1e-9);
        }
    }

    #[test]
    fn underdamped_rise_time_is_shorter() {
        assert!(normalised_rise_time(0.5) < normalised_rise_time(1.0));
    }
}
