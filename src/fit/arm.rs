//! The arm's base parameters and gravity direction from holds, by least squares in force space.
//!
//! Each hold gives three equations F = G(X, v_G) θ ([`Arm::force_regressor`]), weighted by the
//! hold's noise. For a given v_G they are linear in θ: a singular value decomposition of the
//! column-scaled design solves them, drops the directions the holds leave unconstrained (a
//! base moment on a level base has no effect at all: it is unidentifiable, and harmless) and
//! measures the conditioning of the rest. v_G itself, two tilt angles, is found by
//! Levenberg–Marquardt on the residual left after that linear solve (variable projection),
//! started from the arm's own up and from the lattice's v_G.

use nalgebra::{DMatrix, DVector, Vector2, Vector3};

use super::{across, Hold};
use crate::arm::{Arm, ArmGravity, MAX_PARAMETERS};

/// A singular value below this share of the largest, in the column-scaled design, is a
/// direction the holds leave unconstrained: dropped, and reported.
const UNIDENTIFIED: f64 = 1e-6;
/// The largest first moment a parameter may plausibly have, kg m (a kilogram 10 cm out: a
/// desktop arm's links have 0.01–0.03 kg m, the delta's platform 0.03–0.1 kg): a parameter that
/// at this size would move the holds by less than one noise's worth (its noise-weighted column
/// shorter than 1 / this) is unconstrained, as a base moment under a level base is, and dropped
/// rather than fitted to the noise. With a kilogram a metre out, the simulated WoodenHaptics
/// arm's base moment was kept from a base 0.02° off level, fitted to the holds' sub-millinewton
/// noise (−0.006 or −0.03 kg m from one calibration to the next), and a 5° tilt taken in by
/// `hgcd check --apply` then left the whole workspace 2.9–14 % off at p95 (1.7 % with it
/// dropped; docs/calibration.md §2.2).
const PLAUSIBLE_MOMENT: f64 = 0.1;
/// Parameters that act only through a tilt are fitted only where they take more than this from
/// the holds' weighted residual sum of squares, per parameter: about the 1 % point of χ² with 2
/// degrees of freedom, halved (the holds' noise, 0.5 % or 1 mN, is a bound: the simulated
/// linkages' holds are 0.1–0.3 of it, so noise alone takes far less).
const SIGNIFICANT: f64 = 4.6;
/// The fit is refused when the directions it keeps are conditioned worse than this: its
/// parameters would carry the holds' noise, amplified, everywhere the arm goes.
pub const MAX_CONDITION: f64 = 1e4;
/// Levenberg–Marquardt iterations on the tilt, and the step of its finite differences, rad.
const TILT_ITERATIONS: usize = 40;
const TILT_STEP: f64 = 1e-5;
/// The largest tilt of the base the fit looks for, rad.
pub const MAX_TILT: f64 = 0.6;

/// A fitted arm model and what the fit says about itself.
#[derive(Clone, Debug, PartialEq)]
pub struct ArmFit {
    pub gravity: ArmGravity,
    /// How many combinations of the parameters the holds identify.
    pub rank: usize,
    /// The parameter that dominates each combination the holds leave unconstrained.
    pub unidentified: Vec<&'static str>,
    /// Largest over smallest singular value of the identified combinations (column-scaled).
    pub condition: f64,
    /// RMS of |F − F̂| over the holds, N.
    pub rms_residual: f64,
    /// RMS of the residual's components over each hold's noise: about 1 when the model explains
    /// the holds to their noise, well above when it does not (the geometry is off, or a force
    /// the arm does not have: a cable, a spring).
    pub normalised_residual: f64,
    /// Angle between the fitted v_G and the arm's own up, rad.
    pub tilt: f64,
}

/// Why no arm model could be fitted.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum ArmFitError {
    #[error("{have} holds give {equations} equations for {parameters} parameters and the tilt")]
    TooFewHolds {
        have: usize,
        equations: usize,
        parameters: usize,
    },
    #[error(
        "the hold at ({:.1}, {:.1}, {:.1}) mm is out of the arm's reach: the profile's arm is not \
         this device's, or its frame (axes, origin_m) is off",
        position.x * 1e3, position.y * 1e3, position.z * 1e3
    )]
    OutOfReach { position: Vector3<f64> },
    #[error(
        "the holds constrain the arm's parameters poorly (condition {condition:.0}, over \
         {MAX_CONDITION:.0}): hold farther apart in joint angles (a larger calibration.spacing_mm \
         or half_size), away from the workspace's edge"
    )]
    IllConditioned { condition: f64 },
}

/// The linear solve for one v_G.
struct Linear {
    theta: [f64; MAX_PARAMETERS],
    /// Weighted residual, one entry per equation.
    residual: DVector<f64>,
    rank: usize,
    unidentified: Vec<&'static str>,
    condition: f64,
}

/// Fit `arm`'s base parameters and v_G to `holds` under gravity `g` (m/s²), starting the tilt
/// search from each of `starts` (unit vectors, device frame) and keeping the best.
///
/// # Errors
/// [`ArmFitError::TooFewHolds`] for fewer equations than unknowns, [`ArmFitError::OutOfReach`]
/// for a hold the arm cannot be at, [`ArmFitError::IllConditioned`] for holds that pin the
/// parameters too loosely to extrapolate from.
pub fn fit_arm(
    arm: &Arm,
    holds: &[Hold],
    g: f64,
    starts: &[Vector3<f64>],
) -> Result<ArmFit, ArmFitError> {
    let parameters = arm.parameter_count();
    if 3 * holds.len() < parameters + 2 + 1 {
        return Err(ArmFitError::TooFewHolds {
            have: holds.len(),
            equations: 3 * holds.len(),
            parameters,
        });
    }
    // The regressor exists where the arm reaches and J is invertible, whatever v_G.
    let reachable = |h: &&Hold| arm.force_regressor(&h.position, &arm.up(), g).is_some();
    if let Some(h) = holds.iter().find(|h| !reachable(h)) {
        return Err(ArmFitError::OutOfReach {
            position: h.position,
        });
    }
    let best_of = |left_out: &[usize]| {
        let mut best: Option<(Vector3<f64>, Linear)> = None;
        for start in starts {
            let (up, linear) = fit_tilt(arm, holds, g, &start.normalize(), left_out);
            if best
                .as_ref()
                .is_none_or(|(_, b)| linear.residual.norm() < b.residual.norm())
            {
                best = Some((up, linear));
            }
        }
        best.expect("at least one start")
    };
    let (mut up, mut linear) = best_of(&[]);
    // Parameters that act only through a tilt (a serial arm's base moments: nothing under the
    // arm's own up) are kept only where they explain the holds beyond what noise would: from a
    // base a hundredth of a degree off level they fit the holds' noise.
    let level: Vec<_> = holds
        .iter()
        .map(|h| arm.force_regressor(&h.position, &arm.up(), g))
        .collect();
    let tilt_only: Vec<usize> = (0..parameters)
        .filter(|&c| {
            level
                .iter()
                .all(|r| r.is_some_and(|r| r.column(c).norm() == 0.0))
        })
        .collect();
    if !tilt_only.is_empty() {
        let (level_up, level) = best_of(&tilt_only);
        let explained = level.residual.norm_squared() - linear.residual.norm_squared();
        if explained < SIGNIFICANT * tilt_only.len() as f64 {
            (up, linear) = (level_up, level);
        }
    }
    if linear.condition > MAX_CONDITION {
        return Err(ArmFitError::IllConditioned {
            condition: linear.condition,
        });
    }
    let gravity = ArmGravity {
        arm: *arm,
        parameters: linear.theta,
        up,
        g,
    };
    let residuals: Vec<Vector3<f64>> = holds
        .iter()
        .map(|h| h.force - gravity.force(&h.position))
        .collect();
    let rms_residual =
        (residuals.iter().map(|r| r.norm_squared()).sum::<f64>() / holds.len() as f64).sqrt();
    let normalised = residuals
        .iter()
        .zip(holds)
        .map(|(r, h)| r.norm_squared() / (h.noise * h.noise))
        .sum::<f64>()
        / (3 * holds.len()) as f64;
    Ok(ArmFit {
        gravity,
        rank: linear.rank,
        unidentified: linear.unidentified,
        condition: linear.condition,
        rms_residual,
        normalised_residual: normalised.sqrt(),
        tilt: up.angle(&arm.up()),
    })
}

/// v_G near `start` that leaves the least weighted residual, and the linear solve there.
fn fit_tilt(
    arm: &Arm,
    holds: &[Hold],
    g: f64,
    start: &Vector3<f64>,
    left_out: &[usize],
) -> (Vector3<f64>, Linear) {
    let (e1, e2) = across(start);
    let up_at = |t: &Vector2<f64>| (start + e1 * t.x + e2 * t.y).normalize();
    let mut t = Vector2::zeros();
    let mut current = solve(arm, holds, g, &up_at(&t), left_out);
    let mut damping = 1e-3;
    for _ in 0..TILT_ITERATIONS {
        // The residual's Jacobian in the two angles, by central differences.
        let n = current.residual.len();
        let mut jacobian = DMatrix::zeros(n, 2);
        for a in 0..2 {
            let step = Vector2::ith(a, TILT_STEP);
            let plus = solve(arm, holds, g, &up_at(&(t + step)), left_out).residual;
            let minus = solve(arm, holds, g, &up_at(&(t - step)), left_out).residual;
            jacobian.set_column(a, &((plus - minus) / (2.0 * TILT_STEP)));
        }
        let jtj = jacobian.transpose() * &jacobian;
        let jtr = jacobian.transpose() * &current.residual;
        let mut improved = false;
        for _ in 0..8 {
            let mut lhs = jtj.clone();
            for a in 0..2 {
                lhs[(a, a)] += damping * (1.0 + jtj[(a, a)]);
            }
            let Some(step) = lhs.lu().solve(&-&jtr) else {
                damping *= 10.0;
                continue;
            };
            let next_t = t + Vector2::new(step[0], step[1]);
            if next_t.norm() > MAX_TILT.tan() {
                damping *= 10.0;
                continue;
            }
            let next = solve(arm, holds, g, &up_at(&next_t), left_out);
            if next.residual.norm() < current.residual.norm() {
                let converged = step.norm() < 1e-9;
                t = next_t;
                current = next;
                damping = (damping * 0.3).max(1e-9);
                improved = !converged;
                break;
            }
            damping *= 10.0;
        }
        if !improved {
            break;
        }
    }
    (up_at(&t), current)
}

/// The weighted linear least-squares θ for a fixed `up`, the parameters `left_out` held at zero
/// (and reported unidentified).
fn solve(arm: &Arm, holds: &[Hold], g: f64, up: &Vector3<f64>, left_out: &[usize]) -> Linear {
    let p = arm.parameter_count();
    let rows = 3 * holds.len();
    let mut a = DMatrix::zeros(rows, p);
    let mut b = DVector::zeros(rows);
    for (n, h) in holds.iter().enumerate() {
        let regressor = arm
            .force_regressor(&h.position, up, g)
            .expect("holds checked reachable");
        for r in 0..3 {
            for c in 0..p {
                a[(3 * n + r, c)] = regressor[(r, c)] / h.noise;
            }
            b[3 * n + r] = h.force[r] / h.noise;
        }
    }
    // A column far smaller than the others (a base moment under a level base) is as good as
    // absent: its parameter is unconstrained. The rest are scaled to unit norm, so that the
    // singular values compare directions, not units.
    let scale: Vec<f64> = (0..p).map(|c| a.column(c).norm()).collect();
    let largest_column = scale.iter().copied().fold(0.0, f64::max);
    let kept: Vec<usize> = (0..p)
        .filter(|&c| {
            scale[c] > UNIDENTIFIED * largest_column
                && scale[c] * PLAUSIBLE_MOMENT >= 1.0
                && !left_out.contains(&c)
        })
        .collect();
    let mut unidentified: Vec<&'static str> = (0..p)
        .filter(|c| !kept.contains(c))
        .map(|c| arm.parameter_names()[c])
        .collect();
    let mut scaled = DMatrix::zeros(rows, kept.len());
    for (k, &c) in kept.iter().enumerate() {
        scaled.set_column(k, &(a.column(c) / scale[c]));
    }
    if kept.is_empty() {
        return Linear {
            theta: [0.0; MAX_PARAMETERS],
            residual: b,
            rank: 0,
            unidentified,
            condition: f64::INFINITY,
        };
    }
    let svd = scaled.svd(true, true);
    let (u, v_t) = (svd.u.expect("asked for"), svd.v_t.expect("asked for"));
    let sigma = &svd.singular_values;
    let top = sigma.max();
    let mut x = DVector::zeros(kept.len());
    let mut rank = 0;
    let mut smallest_kept = top;
    for k in 0..sigma.len() {
        let direction = v_t.row(k);
        if sigma[k] > UNIDENTIFIED * top {
            rank += 1;
            smallest_kept = smallest_kept.min(sigma[k]);
            x += direction.transpose() * (u.column(k).dot(&b) / sigma[k]);
        } else {
            unidentified.push(arm.parameter_names()[kept[direction.iamax_full().1]]);
        }
    }
    let mut theta = [0.0; MAX_PARAMETERS];
    for (k, &c) in kept.iter().enumerate() {
        theta[c] = x[k] / scale[c];
    }
    let fitted = DVector::from_iterator(p, theta[..p].iter().copied());
    let residual = &b - &a * fitted;
    Linear {
        theta,
        residual,
        rank,
        unidentified,
        condition: top / smallest_kept,
    }
}
