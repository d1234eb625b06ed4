//! The unit's own geometry, near its profile's: where the arm's frame sits, how long its links
//! are.
//!
//! A profile gives the published geometry; a unit differs from it by its manufacturing
//! tolerances (on the simulated units up to 1 mm in where the home pose sits and 0.5 % in each
//! link). The base parameters cannot absorb that: on the delta the profile's geometry leaves
//! 6–9 mN at p95 over the whole workspace, whatever the parameters. With holds as accurate as
//! the strokes along the arm make them (0.1–0.3 %), the geometry itself can be estimated: a
//! Levenberg–Marquardt search over the frame's origin and the link lengths, each step the arm
//! fit's own weighted residual, with a prior that holds each offset to its tolerance (a
//! maximum a posteriori estimate, so a geometry the holds do not pin stays the profile's). The
//! geometry found is kept only where it explains the holds better than the profile's
//! (`EVIDENCE_PER_OFFSET`). docs/calibration.md §13.4 measures what it gains.

use nalgebra::{DMatrix, DVector, Vector3};

use super::arm::{fit_arm, ArmFit, ArmFitError};
use super::Hold;
pub use crate::arm::GeometryTolerances;
use crate::arm::{Arm, ArmGeometry, ArmTable};

/// Levenberg–Marquardt iterations, the trials of damping each may take, and the step of the
/// finite differences (in tolerances).
const ITERATIONS: usize = 12;
const TRIALS: usize = 8;
const STEP: f64 = 1e-3;
/// The search ends when a step improves the cost by less than this share.
const CONVERGED: f64 = 1e-4;
/// A geometry this many tolerances off the profile's is not a unit's spread: the arm is not the
/// profile's (or a force it lacks acts on it). The profile's geometry is kept, and the held-out
/// score judges the arm.
const MAX_TOLERANCES: f64 = 3.0;
/// Offsets all below this share of their tolerances are no move at all.
const MOVED: f64 = 1e-3;
/// Weight of the prior against the holds' residuals, each over its noise. That noise (0.5 % of
/// the force or 1 mN, [`super::HOLD_NOISE_SHARE`]) is a bound: the strokes measure to about
/// 0.13 % RMS of the force (0.075 % per component, docs/calibration.md §4.6), and a unit's
/// offsets spread evenly within their tolerances (σ = t/√3), which would weigh the prior
/// (0.075 / 0.5) √3 ≈ 0.26. At full weight it held a delta unit's geometry halfway to the
/// profile's even from exact holds (3.5 mN at p95 where the unit's own gives none); at 0.26 it
/// followed the less accurate holds of a handle without friction (the delta over 5 mN at p95
/// in 8 runs of 40). Half is the measured middle (docs/calibration.md §13.3).
const PRIOR_WEIGHT: f64 = 0.5;
/// The unit's geometry is kept only where it takes the holds' weighted residual sum of squares
/// down by more than this, per offset: a geometry the holds do not ask for is the profile's.
/// (Measured: 0.2–4.6 on the simulated PHANToM and delta units, which differ from their
/// profiles; under 0.01 on WoodenHaptics', built to theirs, where a moved geometry followed the
/// holds' errors and cost up to 1 mN at p95 over the whole workspace.)
const EVIDENCE_PER_OFFSET: f64 = 0.02;

/// The geometry offsets estimated, and what they did to the fit.
#[derive(Clone, Debug, PartialEq)]
pub struct GeometryShift {
    /// The frame's origin moved by, m (arm frame).
    pub origin: Vector3<f64>,
    /// Each link's length changed by (relative), with its name.
    pub lengths: Vec<(&'static str, f64)>,
    /// The delta's pivots' radius changed by, m.
    pub radius: Option<f64>,
    /// RMS of |F − F̂| over the holds with the profile's geometry, N.
    pub profile_rms_residual: f64,
}

impl GeometryShift {
    /// What moved, in words.
    pub fn describe(&self) -> String {
        let o = self.origin * 1e3;
        let mut out = format!("origin moved ({:.2}, {:.2}, {:.2}) mm", o.x, o.y, o.z);
        for (name, change) in &self.lengths {
            out.push_str(&format!(", {name} {:+.2} %", change * 1e2));
        }
        if let Some(r) = self.radius {
            out.push_str(&format!(", pivots' radius {:+.2} mm", r * 1e3));
        }
        out
    }
}

/// How many geometry offsets `arm` has: origin x, y, z, two lengths, and the delta's radius.
pub fn offsets(arm: &Arm) -> usize {
    match arm.geometry {
        ArmGeometry::Serial(_) => 5,
        ArmGeometry::Delta(_) => 6,
    }
}

/// `arm` with the offsets `p` (each in its tolerance `t`, in [`offsets`]' order) applied.
pub fn placed(arm: &Arm, p: &[f64], t: &GeometryTolerances) -> Arm {
    let mut a = *arm;
    a.frame.origin += Vector3::new(p[0], p[1], p[2]) * t.origin;
    match &mut a.geometry {
        ArmGeometry::Serial(s) => {
            s.upper *= 1.0 + p[3] * t.length;
            s.fore *= 1.0 + p[4] * t.length;
        }
        ArmGeometry::Delta(d) => {
            d.arm *= 1.0 + p[3] * t.length;
            d.rod *= 1.0 + p[4] * t.length;
            d.base_radius += p[5] * t.radius;
        }
    }
    a
}

/// The arm fit's weighted residuals for the geometry `p` (v_G searched from `up`), then the
/// prior's; None where the fit fails there.
fn residual(
    arm: &Arm,
    p: &[f64],
    t: &GeometryTolerances,
    holds: &[Hold],
    g: f64,
    up: &Vector3<f64>,
) -> Option<DVector<f64>> {
    let fit = fit_arm(&placed(arm, p, t), holds, g, &[*up]).ok()?;
    let mut r: Vec<f64> = holds
        .iter()
        .flat_map(|h| {
            let r = (h.force - fit.gravity.force(&h.position)) / h.noise;
            [r.x, r.y, r.z]
        })
        .collect();
    r.extend(p.iter().map(|offset| PRIOR_WEIGHT * offset));
    Some(DVector::from_vec(r))
}

/// Fit `arm`'s base parameters, v_G and geometry to `holds` (tilt searched from each of
/// `starts`, as [`fit_arm`]): the geometry within its `tolerances` of the profile's, the fit
/// with it, and how far it moved; or, where no geometry within `MAX_TOLERANCES` of the
/// profile's explains the holds better (or the tolerances are all 0), [`fit_arm`]'s fit with
/// the profile's geometry and None.
///
/// # Errors
/// [`fit_arm`]'s, with the profile's geometry.
pub fn fit_arm_and_geometry(
    arm: &Arm,
    holds: &[Hold],
    g: f64,
    starts: &[Vector3<f64>],
    tolerances: &GeometryTolerances,
) -> Result<(ArmFit, Option<GeometryShift>), ArmFitError> {
    let t = tolerances;
    let profile = fit_arm(arm, holds, g, starts)?;
    if t.exact() {
        return Ok((profile, None));
    }
    let up = profile.gravity.up;
    let n = offsets(arm);
    let mut p = vec![0.0; n];
    // The fit from the profile's v_G alone may still fail (conditioning near its bound).
    let Some(mut current) = residual(arm, &p, t, holds, g, &up) else {
        return Ok((profile, None));
    };
    let mut damping = 1e-2;
    for _ in 0..ITERATIONS {
        let mut jacobian = DMatrix::zeros(current.len(), n);
        for k in 0..n {
            let (mut plus, mut minus) = (p.clone(), p.clone());
            plus[k] += STEP;
            minus[k] -= STEP;
            let (Some(a), Some(b)) = (
                residual(arm, &plus, t, holds, g, &up),
                residual(arm, &minus, t, holds, g, &up),
            ) else {
                return Ok((profile, None));
            };
            jacobian.set_column(k, &((a - b) / (2.0 * STEP)));
        }
        let jtj = jacobian.transpose() * &jacobian;
        let jtr = jacobian.transpose() * &current;
        let cost = current.norm_squared();
        let mut improved = None;
        for _ in 0..TRIALS {
            let mut lhs = jtj.clone();
            for k in 0..n {
                lhs[(k, k)] += damping * (1.0 + jtj[(k, k)]);
            }
            let Some(step) = lhs.lu().solve(&-&jtr) else {
                damping *= 10.0;
                continue;
            };
            let next: Vec<f64> = p.iter().zip(step.iter()).map(|(a, b)| a + b).collect();
            match residual(arm, &next, t, holds, g, &up) {
                Some(r) if r.norm_squared() < cost => {
                    improved = Some((next, r));
                    damping *= 0.3;
                    break;
                }
                _ => damping *= 10.0,
            }
        }
        let Some((next, r)) = improved else { break };
        let gain = (cost - r.norm_squared()) / cost.max(f64::MIN_POSITIVE);
        (p, current) = (next, r);
        if gain < CONVERGED {
            break;
        }
    }
    // Unmoved, beyond a unit's spread, or a geometry the grid file would refuse: the profile's.
    let moved = p.iter().any(|v| v.abs() > MOVED);
    let beyond = p.iter().any(|v| v.abs() > MAX_TOLERANCES);
    let placed = placed(arm, &p, t);
    let storable = ArmTable::of(&placed).arm().is_ok();
    let fitted = match fit_arm(&placed, holds, g, &[up]) {
        Ok(fit) if moved && !beyond && storable => fit,
        _ => return Ok((profile, None)),
    };
    // Each fit's weighted residual sum of squares over the holds, from its own figure.
    let weighted_rss = |fit: &ArmFit| fit.normalised_residual.powi(2) * (3 * holds.len()) as f64;
    if weighted_rss(&profile) - weighted_rss(&fitted) < EVIDENCE_PER_OFFSET * n as f64 {
        return Ok((profile, None));
    }
    let shift = shift_of(arm, &p, t, &profile);
    Ok((fitted, Some(shift)))
}

/// The shift the offsets `p` describe, with the profile's fit's residual.
fn shift_of(arm: &Arm, p: &[f64], t: &GeometryTolerances, profile: &ArmFit) -> GeometryShift {
    let lengths = match arm.geometry {
        ArmGeometry::Serial(_) => {
            vec![("upper arm", p[3] * t.length), ("forearm", p[4] * t.length)]
        }
        ArmGeometry::Delta(_) => vec![("arms", p[3] * t.length), ("rods", p[4] * t.length)],
    };
    GeometryShift {
        origin: Vector3::new(p[0], p[1], p[2]) * t.origin,
        lengths,
        radius: matches!(arm.geometry, ArmGeometry::Delta(_)).then(|| p[5] * t.radius),
        profile_rms_residual: profile.rms_residual,
    }
}
