//! The next vertex's holding force predicted from the arm's gravity, fitted as vertices are
//! measured.
//!
//! Each measured vertex gives three equations F = G(X, v_G) θ in the arm's base parameters θ
//! ([`Arm::force_regressor`]). G is linear in the gravity direction, G(X, v) = Σₖ vₖ Gₖ(X) with
//! Gₖ the regressor for gravity along the device's axis k, so the sums Σ Gₖᵀ Gₗ and Σ Gₖᵀ F over
//! the holds hold everything a fit needs whatever v_G is: they are summed as vertices come in,
//! and after each one θ and v_G are found from them: θ by least squares for a given v_G, v_G by
//! a Newton search over the base's two tilt angles, from the arm's own up. A tilted base is then
//! predicted as well as a level one. Fixed-size and allocation-free: it runs on the servo thread.
//! The full fit after the run ([`crate::fit::arm`]) also tells what the holds identify; this one
//! only needs to land the strokes' feedforward within their tolerance.

use nalgebra::{Matrix2, SMatrix, Vector2, Vector3};

use crate::arm::{Arm, ForceRegressor, MAX_PARAMETERS};

type Normal = SMatrix<f64, MAX_PARAMETERS, MAX_PARAMETERS>;
type Column = SMatrix<f64, MAX_PARAMETERS, 1>;

/// Ridge added to the normal equations, N² per parameter unit squared: a parameter of
/// `RIDGE_SCALE` (kg m, or kg) that would move the holds by less than `RIDGE_NOISE` (N) is held
/// near zero. It pins what the holds leave unconstrained (a base moment under a level base has
/// no column at all, and under a base tilted by a hair a column so small that any residual would
/// make it huge) without moving the rest (the simulated arms' columns are tens of newtons per kg
/// m, their moments under 0.01 kg m).
const RIDGE_NOISE: f64 = 1e-4;
const RIDGE_SCALE: f64 = 0.1;
/// A fit whose holds' residual per degree of freedom it leaves exceeds this (RMS) predicts
/// nothing, N: its arm is not this device's, and the neighbours predict as well. The strokes
/// tolerate a feedforward 30 mN off (`STROKE_REPEAT` in `control/calibration/machine/mod.rs`); the simulated linkages'
/// holds leave 0.2–2.5 mN.
const MAX_RESIDUAL: f64 = 0.01;
/// Newton steps over the tilt at most, the step (rad) below which they stop, the angle of the
/// central differences (rad), and the range of the steps' damping (share of the Hessian).
const TILT_STEPS: usize = 12;
const CONVERGED: f64 = 1e-9;
const DIFFERENCE: f64 = 1e-4;
const MIN_DAMPING: f64 = 1e-9;
const MAX_DAMPING: f64 = 1e6;
/// The coarse grid of tilts the search starts from: this many along each of the two angles,
/// this far apart (tan 5°: ±15° in all). About 20 µs a hold with the Newton steps.
const GRID_SIDE: usize = 7;
const GRID_STEP: f64 = 0.0875;
/// A gravity direction further than this from the arm's up (cos) is not a tilted base but a
/// fit gone astray: the full fit's reach (34°).
const MAX_TILT_COS: f64 = 0.829;

/// The sums of the arm's regressors over the vertices measured so far, and the fit they give.
#[derive(Clone, Copy, Debug)]
pub struct ArmPrediction {
    arm: Arm,
    /// m/s².
    g: f64,
    /// Σ Gₖᵀ Gₗ over the holds, k, l the device's axes.
    cross: [[Normal; 3]; 3],
    /// Σ Gₖᵀ F over the holds.
    right: [Column; 3],
    /// Σ |F|² over the holds, N², for the residual.
    squares: f64,
    holds: usize,
    /// The fit to the holds so far, if it explains them: θ and v_G.
    fit: Option<(Column, Vector3<f64>)>,
}

impl ArmPrediction {
    pub fn new(arm: Arm, g: f64) -> Self {
        Self {
            arm,
            g,
            cross: [[Normal::zeros(); 3]; 3],
            right: [Column::zeros(); 3],
            squares: 0.0,
            holds: 0,
            fit: None,
        }
    }

    /// Gₖ at `x` for gravity along each of the device's axes; None out of reach.
    fn regressors(&self, x: &Vector3<f64>) -> Option<[ForceRegressor; 3]> {
        Some([
            self.arm.force_regressor(x, &Vector3::x(), self.g)?,
            self.arm.force_regressor(x, &Vector3::y(), self.g)?,
            self.arm.force_regressor(x, &Vector3::z(), self.g)?,
        ])
    }

    /// Take in the force `force` measured with the handle at `x` (m, N), and fit again. A
    /// position out of the arm's reach is left out.
    pub fn add(&mut self, x: &Vector3<f64>, force: &Vector3<f64>) {
        let Some(r) = self.regressors(x) else {
            return;
        };
        for k in 0..3 {
            for l in 0..3 {
                self.cross[k][l] += r[k].transpose() * r[l];
            }
            self.right[k] += r[k].transpose() * force;
        }
        self.squares += force.norm_squared();
        self.holds += 1;
        self.fit = self.solve();
    }

    /// θ for gravity along `v`, and the holds' Σ |F − G θ|² it leaves.
    fn parameters_for(&self, v: &Vector3<f64>) -> Option<(Column, f64)> {
        let mut normal = Normal::zeros();
        let mut right = Column::zeros();
        for k in 0..3 {
            for l in 0..3 {
                normal += self.cross[k][l] * (v[k] * v[l]);
            }
            right += self.right[k] * v[k];
        }
        let ridge = (RIDGE_NOISE / RIDGE_SCALE).powi(2);
        let ridged = normal + Normal::identity() * ridge;
        let theta = ridged.cholesky()?.solve(&right);
        // Σ |F − G θ|² = Σ |F|² − 2 θᵀ Σ Gᵀ F + θᵀ (Σ GᵀG) θ.
        let residual =
            self.squares - 2.0 * theta.dot(&right) + (theta.transpose() * normal * theta)[0];
        Some((theta, residual.max(0.0)))
    }

    /// θ and v_G: θ by least squares for each v_G tried, v_G by a damped Newton search over the
    /// base's two tilt angles on the residual that leaves. None with fewer equations than the
    /// parameters and two (3 holds for the delta's 7, the serial arm's 6), a tilt beyond the
    /// full fit's reach, or a residual beyond [`MAX_RESIDUAL`]. Until the holds give three
    /// equations more than that (the fourth hold), v_G stays the arm's up: the tilt would fit
    /// the noise.
    fn solve(&self) -> Option<(Column, Vector3<f64>)> {
        let equations = 3 * self.holds;
        let parameters = self.arm.parameter_count();
        if equations < parameters + 2 {
            return None;
        }
        let up = self.arm.up();
        let tilted = equations >= parameters + 2 + 3;
        let (e1, e2) = crate::fit::across(&up);
        let direction = |a: f64, b: f64| (up + e1 * a + e2 * b).normalize();
        let cost = |a: f64, b: f64| self.parameters_for(&direction(a, b)).map(|(_, r)| r);
        // The residual has a cusp at the arm's up (a serial arm's base moments act only through
        // the tilt): start from the best of a coarse grid of tilts.
        let (mut a, mut b) = (0.0, 0.0);
        let mut here = cost(a, b)?;
        if tilted {
            let half = (GRID_SIDE / 2) as f64;
            for n in 0..GRID_SIDE * GRID_SIDE {
                let ga = ((n % GRID_SIDE) as f64 - half) * GRID_STEP;
                let gb = ((n / GRID_SIDE) as f64 - half) * GRID_STEP;
                let there = cost(ga, gb)?;
                if there < here {
                    (a, b, here) = (ga, gb, there);
                }
            }
        }
        let mut damping = 1e-3;
        for _ in 0..if tilted { TILT_STEPS } else { 0 } {
            // Gradient and Hessian of the residual by central differences.
            let h = DIFFERENCE;
            let (fa, fa_) = (cost(a + h, b)?, cost(a - h, b)?);
            let (fb, fb_) = (cost(a, b + h)?, cost(a, b - h)?);
            let fab = cost(a + h, b + h)? - cost(a + h, b - h)? - cost(a - h, b + h)?
                + cost(a - h, b - h)?;
            let gradient = Vector2::new(fa - fa_, fb - fb_) / (2.0 * h);
            let hessian = Matrix2::new(
                (fa - 2.0 * here + fa_) / (h * h),
                fab / (4.0 * h * h),
                fab / (4.0 * h * h),
                (fb - 2.0 * here + fb_) / (h * h),
            );
            let scale = hessian.diagonal().abs().max().max(f64::MIN_POSITIVE);
            let mut stepped = false;
            while damping < MAX_DAMPING {
                let damped = hessian + Matrix2::identity() * (damping * scale);
                let Some(step) = damped.cholesky().map(|c| c.solve(&-gradient)) else {
                    damping *= 10.0;
                    continue;
                };
                let there = cost(a + step.x, b + step.y)?;
                if there < here {
                    (a, b, here) = (a + step.x, b + step.y, there);
                    damping = (damping / 10.0).max(MIN_DAMPING);
                    stepped = step.norm() > CONVERGED;
                    break;
                }
                damping *= 10.0;
            }
            if !stepped {
                break;
            }
        }
        let v = direction(a, b);
        if v.dot(&up) < MAX_TILT_COS {
            return None;
        }
        let (theta, residual) = self.parameters_for(&v)?;
        // Per degree of freedom the fit leaves, so that its first holds, which the parameters
        // nearly fit whatever they are, do not pass for well explained. (NaN fails too.)
        let free = if tilted { parameters + 2 } else { parameters };
        let variance = residual / (equations - free) as f64;
        (variance <= MAX_RESIDUAL * MAX_RESIDUAL).then_some((theta, v))
    }

    /// The force that holds the handle at `x` by the fit to the holds so far; None where there
    /// is no fit (`Self::solve`) or out of reach.
    pub fn predict(&self, x: &Vector3<f64>) -> Option<Vector3<f64>> {
        let (theta, v) = self.fit?;
        let r = self.arm.force_regressor(x, &v, self.g)?;
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

    /// The same arms on a base tilted 10° (the serial arm's base moments then act): the first
    /// four vertices predict every vertex of the cube within 10 µN, where the arm's own up
    /// leaves tens of millinewtons.
    #[test]
    fn four_holds_of_a_tilted_arm_predict_its_whole_cube() {
        let tilt = nalgebra::Rotation3::from_axis_angle(
            &nalgebra::Unit::new_normalize(Vector3::new(1.0, 2.0, 0.0)),
            10f64.to_radians(),
        );
        let mut phantom = phantom_gravity();
        phantom.parameters[4] = 0.002;
        phantom.parameters[5] = -0.001;
        let cases: [(ArmGravity, Vector3<f64>); 2] = [
            (phantom, Vector3::new(-0.033, 0.0, 0.032)),
            (delta_gravity(), Vector3::zeros()),
        ];
        for (level, centre) in cases {
            let truth = ArmGravity {
                up: tilt * level.up,
                ..level
            };
            let points = cube(centre);
            let mut fit = ArmPrediction::new(truth.arm, truth.g);
            for x in &points[..4] {
                fit.add(x, &truth.force(x));
            }
            let (_, v) = fit.fit.unwrap();
            assert!(
                v.angle(&truth.up) < 1e-5,
                "{}: v_G {v:?}, {} rad off",
                truth.arm.kind(),
                v.angle(&truth.up)
            );
            for x in &points {
                let error = (fit.predict(x).unwrap() - truth.force(x)).norm();
                assert!(error < 1e-5, "{} at {x:?}: {error} N", truth.arm.kind());
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
