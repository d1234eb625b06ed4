//! The next vertex's holding force predicted from the arm's gravity, fitted as vertices are
//! measured.
//!
//! Each measured vertex gives three equations F = G(X) θ in the arm's base parameters θ
//! ([`Arm::force_regressor`], v_G the arm's own up): their normal equations are summed as
//! vertices come in, and solved for θ when a prediction is asked for. Fixed-size and
//! allocation-free: it runs on the servo thread. The full fit after the run
//! ([`crate::fit::arm`]) also finds the tilt and tells what the holds identify; this one only
//! needs to land the strokes' feedforward within their tolerance.

use nalgebra::{SMatrix, Vector3};

use crate::arm::{Arm, MAX_PARAMETERS};

type Normal = SMatrix<f64, MAX_PARAMETERS, MAX_PARAMETERS>;
type Column = SMatrix<f64, MAX_PARAMETERS, 1>;

/// Ridge added to the normal equations, as a share of their mean diagonal: it pins what the
/// holds leave unconstrained (a base moment under a level base has no column at all) to zero
/// without moving the rest.
const RIDGE: f64 = 1e-9;
/// A fit whose holds' residual per degree of freedom it leaves exceeds this (RMS) predicts
/// nothing, N: its arm is not
/// this device's, or the base is tilted far, and the neighbours predict as well. The strokes
/// tolerate a feedforward 30 mN off (`STROKE_REPEAT` in `machine.rs`); the simulated linkages'
/// holds leave 0.2–2.5 mN.
const MAX_RESIDUAL: f64 = 0.01;

/// The normal equations of the arm's base parameters over the vertices measured so far.
#[derive(Clone, Copy, Debug)]
pub(super) struct ArmPrediction {
    arm: Arm,
    /// m/s².
    g: f64,
    normal: Normal,
    right: Column,
    /// Σ |F|² over the holds, N², for the residual.
    squares: f64,
    holds: usize,
}

impl ArmPrediction {
    pub fn new(arm: Arm, g: f64) -> Self {
        Self {
            arm,
            g,
            normal: Normal::zeros(),
            right: Column::zeros(),
            squares: 0.0,
            holds: 0,
        }
    }

    /// Take in the force `force` measured with the handle at `x` (m, N). A position out of the
    /// arm's reach is left out.
    pub fn add(&mut self, x: &Vector3<f64>, force: &Vector3<f64>) {
        if let Some(r) = self.arm.force_regressor(x, &self.arm.up(), self.g) {
            self.normal += r.transpose() * r;
            self.right += r.transpose() * force;
            self.squares += force.norm_squared();
            self.holds += 1;
        }
    }

    /// The force that holds the handle at `x` by the parameters that fit the holds so far;
    /// None with fewer equations than parameters and the tilt the full fit finds (3 holds for the
    /// delta's 7, the serial arm's 6), where the fit leaves more than [`MAX_RESIDUAL`], or out
    /// of reach.
    pub fn predict(&self, x: &Vector3<f64>) -> Option<Vector3<f64>> {
        let equations = 3 * self.holds;
        let parameters = self.arm.parameter_count();
        if equations < parameters + 2 {
            return None;
        }
        let scale = self.normal.trace() / MAX_PARAMETERS as f64;
        let ridged = self.normal + Normal::identity() * (RIDGE * scale);
        let theta = ridged.cholesky()?.solve(&self.right);
        // Σ |F − G θ|² = Σ |F|² − 2 θᵀ Σ Gᵀ F + θᵀ (Σ GᵀG) θ.
        let residual = self.squares - 2.0 * theta.dot(&self.right)
            + (theta.transpose() * self.normal * theta)[0];
        // Per degree of freedom the fit leaves, so that its first holds, which the parameters
        // nearly fit whatever they are, do not pass for well explained. (NaN fails too.)
        let variance = residual.max(0.0) / (equations - parameters) as f64;
        if variance.is_nan() || variance > MAX_RESIDUAL * MAX_RESIDUAL {
            return None;
        }
        let r = self.arm.force_regressor(x, &self.arm.up(), self.g)?;
        Some(r * theta).filter(|f| f.iter().all(|c| c.is_finite()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::arm::tests::{delta_gravity, phantom_gravity};
    use crate::arm::ArmGravity;

    /// The 27 vertices of a 40 mm cube around `centre`.
    fn cube(centre: Vector3<f64>) -> Vec<Vector3<f64>> {
        let steps = [-1.0, 0.0, 1.0];
        let mut points = Vec::new();
        for k in steps {
            for j in steps {
                for i in steps {
                    points.push(centre + Vector3::new(i, j, k) * 0.04);
                }
            }
        }
        points
    }

    /// Arms of known parameters: the first three vertices of a run predict every vertex of the
    /// cube within 10 µN (the forces are 0.1–1 N).
    #[test]
    fn three_holds_of_an_arm_predict_its_whole_cube() {
        let cases: [(ArmGravity, Vector3<f64>); 2] = [
            (phantom_gravity(), Vector3::new(-0.033, 0.0, 0.032)),
            (delta_gravity(), Vector3::zeros()),
        ];
        for (truth, centre) in cases {
            let points = cube(centre);
            let mut fit = ArmPrediction::new(truth.arm, truth.g);
            assert_eq!(fit.predict(&points[0]), None, "no holds, no prediction");
            for x in &points[..2] {
                fit.add(x, &truth.force(x));
            }
            assert_eq!(fit.predict(&points[0]), None, "two holds are too few");
            fit.add(&points[2], &truth.force(&points[2]));
            for x in &points {
                let error = (fit.predict(x).unwrap() - truth.force(x)).norm();
                assert!(error < 1e-5, "{:?} at {x:?}: {error} N", truth.arm.kind());
            }
        }
    }

    /// Holds that the arm cannot explain (a spring of 20 N/m toward the cube's centre on top of
    /// its gravity: 0.8–1.4 N at the vertices) leave a residual beyond what the strokes
    /// tolerate: no prediction.
    #[test]
    fn holds_the_arm_does_not_explain_predict_nothing() {
        let truth = phantom_gravity();
        let points = cube(Vector3::new(-0.033, 0.0, 0.032));
        let mut fit = ArmPrediction::new(truth.arm, truth.g);
        for x in &points {
            fit.add(x, &(truth.force(x) + 20.0 * (points[13] - x)));
        }
        assert_eq!(fit.predict(&points[13]), None);
    }
}
