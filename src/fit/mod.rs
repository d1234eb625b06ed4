//! Gravity models fitted from holds, and the held-out score that chooses among them.
//!
//! Calibration measures *holds*: where the handle was held and the force that held it there.
//! This module turns them into the parameters of a model, off the servo thread (all but
//! [`predict`], which the calibration runs on it as holds come in):
//! - the paper's scalar lattice (M(X) g v_G) and the vector lattice (the holding forces
//!   themselves), interpolated trilinearly: they need no knowledge of the device, and hold
//!   nothing beyond the calibrated cube;
//! - the arm model ([`arm::fit_arm`]): for a device whose profile gives its kinematics, the
//!   base parameters of its links' weight and the gravity direction, which fix the holding
//!   force everywhere the arm can go;
//! - the arm model plus a lattice of what it leaves over (a cable's spring, a counterweight's
//!   sag), inside the cube, fading out over one spacing beyond it.
//!
//! Some holds are kept out of every fit; each candidate is scored on them
//! ([`choose`]) and the best is used. `control::compensation::GravityModel` evaluates the one
//! chosen.
//!
//! The parts: [`lattice`] (the holds at a grid's vertices completed into the grid both lattices
//! interpolate), [`arm`] (the arm model's fit), [`geometry`] (the unit's own geometry),
//! [`predict`] (the arm's gravity fitted as a calibration's holds come in, to predict the next
//! one) and this file (the held-out choice).

pub mod arm;
pub mod geometry;
pub mod lattice;
pub mod predict;

use nalgebra::Vector3;

use crate::arm::Arm;
use crate::config::CompensationMode;
use crate::grid::{extrapolate_from_neighbours, fill_from_neighbours};
pub use arm::{fit_arm, ArmFit, ArmFitError};
pub use geometry::{fit_arm_and_geometry, GeometryShift, GeometryTolerances};

/// A hold's noise: this share of its force, or this floor, whichever is larger (the accuracy
/// of the friction-robust hold, docs/calibration.md §6), N.
pub const HOLD_NOISE_SHARE: f64 = 0.005;
pub const HOLD_NOISE_FLOOR_N: f64 = 0.001;

/// One in this many holds is kept out of the fits and scores them.
pub const HELD_OUT_EVERY: usize = 4;

/// A candidate within this many percentage points of the best held-out score (or 10 % of it,
/// whichever is more) counts as good as the best; among those, the model that covers the whole
/// workspace is used.
pub const SCORE_TOLERANCE_PCT: f64 = 0.25;

/// The arm model is judged off when it explains the holds this many times worse than their
/// noise (RMS of the residual's components over each hold's noise).
pub const RESIDUAL_ABOVE_NOISE: f64 = 2.0;

/// Two unit vectors spanning the plane across `up` (a tilt of `up` is a step in that plane).
pub fn across(up: &Vector3<f64>) -> (Vector3<f64>, Vector3<f64>) {
    let helper = if up.x.abs() < 0.9 {
        Vector3::x()
    } else {
        Vector3::y()
    };
    let e1 = up.cross(&helper).normalize();
    (e1, up.cross(&e1))
}

/// A holding force measured at a position (device frame, SI).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hold {
    pub position: Vector3<f64>,
    pub force: Vector3<f64>,
    /// Standard deviation of each component of `force`, N.
    pub noise: f64,
}

impl Hold {
    /// A hold with the calibration's noise ([`HOLD_NOISE_SHARE`], [`HOLD_NOISE_FLOOR_N`]).
    pub fn new(position: Vector3<f64>, force: Vector3<f64>) -> Self {
        Self {
            position,
            force,
            noise: (force.norm() * HOLD_NOISE_SHARE).max(HOLD_NOISE_FLOOR_N),
        }
    }
}

/// The holds of a lattice calibration: one per vertex the handle was held at.
#[derive(Clone, Debug, PartialEq)]
pub struct LatticeHolds {
    /// Vertices along x, y, z (grid order, x fastest).
    pub dims: [usize; 3],
    /// Each vertex's position, m.
    pub positions: Vec<Vector3<f64>>,
    /// Each vertex's hold carried to the vertex (what the lattices interpolate); None where the
    /// handle was not held (unreachable, extrapolated).
    pub holds: Vec<Option<Hold>>,
    /// The same holds where they were measured, a millimetre or two off the vertex (what the
    /// arm model is fitted to).
    pub measured: Vec<Option<Hold>>,
    /// The lattice's v_G (the scalar mode's direction) and g, m/s².
    pub up: Vector3<f64>,
    pub g: f64,
    /// How the lattice fills the vertices it did not hold, as the calibration filled them:
    /// along straight lines (an explored grid) or with its neighbours' mean.
    pub linear_fill: bool,
}

/// Held-out scores: 100 √(Σ|F − F̂|² / Σ|F|²) over the held-out holds, %; None for a model that
/// could not be fitted.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Scores {
    pub scalar: f64,
    pub vector: f64,
    pub arm: Option<f64>,
    pub arm_residual: Option<f64>,
}

impl Scores {
    /// The score of `mode`.
    pub fn of(&self, mode: CompensationMode) -> Option<f64> {
        match mode {
            CompensationMode::Scalar => Some(self.scalar),
            CompensationMode::Vector => Some(self.vector),
            CompensationMode::Arm => self.arm,
            CompensationMode::ArmResidual => self.arm_residual,
        }
    }
}

/// The model chosen for a calibration, and why.
#[derive(Clone, Debug, PartialEq)]
pub struct Choice {
    pub mode: CompensationMode,
    pub scores: Scores,
    /// Holds kept out of the fits.
    pub held_out: usize,
    /// The arm model fitted to every hold (None without an arm), its geometry estimated
    /// within the unit's tolerances of the profile's ([`geometry`]) ...
    pub arm: Option<Result<ArmFit, ArmFitError>>,
    /// ... and how far that geometry moved.
    pub geometry: Option<GeometryShift>,
}

impl Choice {
    /// A sentence on the arm model when it was not chosen or is off (None when all is well).
    pub fn warning(&self) -> Option<String> {
        let fit = match &self.arm {
            None => return None,
            Some(Err(e)) => return Some(format!("the arm model was not used: {e}")),
            Some(Ok(fit)) => fit,
        };
        if !matches!(
            self.mode,
            CompensationMode::Arm | CompensationMode::ArmResidual
        ) {
            return Some(format!(
                "the arm model scored {:.1} % on the held-out holds against the {} lattice's \
                 {:.1} %: the profile's arm does not describe this device (check device.profile); \
                 the lattice compensates, inside the calibrated cube only",
                self.scores.arm.unwrap_or(f64::NAN),
                self.mode,
                self.scores.of(self.mode).unwrap_or(f64::NAN),
            ));
        }
        (fit.normalised_residual > RESIDUAL_ABOVE_NOISE).then(|| {
            format!(
                "the arm model leaves {:.1} times the holds' noise ({:.1} mN RMS): the arm's \
                 geometry in the profile is off, or a force the arm model lacks acts on it \
                 (a cable, a spring)",
                fit.normalised_residual,
                fit.rms_residual * 1e3
            )
        })
    }
}

/// 100 √(Σ|F − F̂|² / Σ|F|²) over (measured F, predicted F̂) pairs, %.
fn score(pairs: impl Iterator<Item = (Vector3<f64>, Vector3<f64>)>) -> f64 {
    let (error, size) = pairs.fold((0.0, 0.0), |(e, s), (f, p)| {
        (e + (f - p).norm_squared(), s + f.norm_squared())
    });
    100.0 * (error / f64::max(size, f64::MIN_POSITIVE)).sqrt()
}

/// Score the candidates on held-out holds and choose: every [`HELD_OUT_EVERY`]-th measured hold
/// (the second, the sixth, …) is kept out; the lattices predict it from their neighbours (as
/// they fill a vertex not held, [`LatticeHolds::linear_fill`]), the arm
/// model from its fit to the others. Without `arm` the vector lattice is chosen (the scalar one
/// without holds to score), as before arm models existed. The arm model returned is fitted to
/// every hold, with the unit's own geometry within `tolerances` of the profile's where that
/// scores no worse.
pub fn choose(
    lattice: &LatticeHolds,
    arm: Option<&Arm>,
    tolerances: &GeometryTolerances,
) -> Choice {
    let measured: Vec<usize> = (0..lattice.holds.len())
        .filter(|&n| lattice.holds[n].is_some())
        .collect();
    let held_out: Vec<usize> = measured
        .iter()
        .copied()
        .skip(1)
        .step_by(HELD_OUT_EVERY)
        .collect();
    let training: Vec<bool> = (0..lattice.holds.len())
        .map(|n| lattice.holds[n].is_some() && !held_out.contains(&n))
        .collect();
    // A lattice's prediction of each held-out hold, against the hold carried to its vertex.
    let score_at_vertices = |predicted: &[Vector3<f64>]| {
        score(held_out.iter().map(|&n| {
            let hold = lattice.holds[n].expect("measured");
            (hold.force, predicted[n])
        }))
    };
    // The lattices: the held-out vertices filled from the training ones.
    let forces: Vec<Vector3<f64>> = lattice
        .holds
        .iter()
        .map(|h| h.map_or(Vector3::zeros(), |h| h.force))
        .collect();
    let filled = |values: &[Vector3<f64>]| {
        let mut values = values.to_vec();
        if training.contains(&true) {
            if lattice.linear_fill {
                extrapolate_from_neighbours(lattice.dims, &mut values, &training);
            } else {
                fill_from_neighbours(lattice.dims, &mut values, &training);
            }
        }
        values
    };
    let vector = filled(&forces);
    let scalar: Vec<Vector3<f64>> = filled(
        &forces
            .iter()
            .map(|f| lattice.up * f.dot(&lattice.up))
            .collect::<Vec<_>>(),
    );
    let mut scores = Scores {
        scalar: score_at_vertices(&scalar),
        vector: score_at_vertices(&vector),
        ..Scores::default()
    };
    let Some(arm) = arm else {
        return Choice {
            mode: CompensationMode::Vector,
            scores,
            held_out: held_out.len(),
            arm: None,
            geometry: None,
        };
    };
    let starts = [arm.up(), lattice.up];
    let raw = |n: usize| lattice.measured[n].or(lattice.holds[n]).expect("measured");
    let train: Vec<Hold> = (0..training.len())
        .filter(|&n| training[n])
        .map(raw)
        .collect();
    let held_out_score = |fit: &ArmFit| {
        score(held_out.iter().map(|&n| {
            let hold = raw(n);
            (hold.force, fit.gravity.force(&hold.position))
        }))
    };
    // The profile's geometry and the unit's own (geometry.rs), each fitted to the training holds
    // and scored where the held-out ones were measured: the unit's is kept only where it scores
    // no worse.
    let profile_fit = fit_arm(arm, &train, lattice.g, &starts).ok();
    let unit_fit = fit_arm_and_geometry(arm, &train, lattice.g, &starts, tolerances)
        .ok()
        .and_then(|(fit, shift)| shift.map(|_| fit));
    let unit_geometry = match (&profile_fit, &unit_fit) {
        (Some(profile), Some(unit)) => held_out_score(unit) <= held_out_score(profile),
        (None, Some(_)) => true,
        _ => false,
    };
    let trained = if unit_geometry { unit_fit } else { profile_fit };
    if let Some(fit) = trained {
        scores.arm = Some(held_out_score(&fit));
        let model = |x: &Vector3<f64>| fit.gravity.force(x);
        let at_vertices: Vec<Vector3<f64>> = lattice.positions.iter().map(model).collect();
        let residual: Vec<Vector3<f64>> = (0..forces.len())
            .map(|n| forces[n] - at_vertices[n])
            .collect();
        let residual = filled(&residual);
        let with_residual: Vec<Vector3<f64>> = (0..forces.len())
            .map(|n| at_vertices[n] + residual[n])
            .collect();
        scores.arm_residual = Some(score_at_vertices(&with_residual));
    }
    let all: Vec<Hold> = measured.iter().map(|&n| raw(n)).collect();
    let (full, geometry) = if unit_geometry {
        match fit_arm_and_geometry(arm, &all, lattice.g, &starts, tolerances) {
            Ok((fit, shift)) => (Ok(fit), shift),
            Err(e) => (Err(e), None),
        }
    } else {
        (fit_arm(arm, &all, lattice.g, &starts), None)
    };
    let mode = preferred(&scores, full.is_ok());
    Choice {
        mode,
        scores,
        held_out: held_out.len(),
        arm: Some(full),
        geometry,
    }
}

/// The candidate used: the best held-out score, or among those within the tolerance of it the
/// model that covers the whole workspace (arm, then arm + residual, then the lattices), unless
/// the arm alone predicts worse than the vector lattice by more than that tolerance. Then the
/// arm has failed (the wrong arm named, or its geometry far off), what the arm + residual
/// model gets right its residual lattice gets right, and the lattices win the tie (the delta's
/// profile on the simulated PHANToM: vector 36 %, arm 58 %, arm + residual 42 %, and in one
/// calibration 39.7 %, within the tolerance). The arm models count only where `arm_fitted`
/// (their fit to every hold).
fn preferred(scores: &Scores, arm_fitted: bool) -> CompensationMode {
    let within = |score: f64| SCORE_TOLERANCE_PCT.max(0.1 * score);
    let arm_failed = scores
        .arm
        .is_some_and(|arm| arm > scores.vector + within(scores.vector));
    let order = if arm_failed {
        [
            CompensationMode::Vector,
            CompensationMode::Scalar,
            CompensationMode::ArmResidual,
            CompensationMode::Arm,
        ]
    } else {
        [
            CompensationMode::Arm,
            CompensationMode::ArmResidual,
            CompensationMode::Vector,
            CompensationMode::Scalar,
        ]
    };
    let usable = |m: &CompensationMode| match m {
        CompensationMode::Arm | CompensationMode::ArmResidual => arm_fitted,
        _ => true,
    };
    let best = order
        .iter()
        .filter(|m| usable(m))
        .filter_map(|&m| scores.of(m))
        .fold(f64::INFINITY, f64::min);
    let tolerance = within(best);
    order
        .into_iter()
        .filter(|m| usable(m))
        .find(|&m| scores.of(m).is_some_and(|s| s <= best + tolerance))
        .unwrap_or(CompensationMode::Vector)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scores(scalar: f64, vector: f64, arm: f64, arm_residual: f64) -> Scores {
        Scores {
            scalar,
            vector,
            arm: Some(arm),
            arm_residual: Some(arm_residual),
        }
    }

    #[test]
    fn the_model_covering_the_workspace_wins_a_tie_unless_its_arm_failed() {
        use CompensationMode::*;
        // sim:phantom unit 1 with its own profile (docs/calibration.md §13.2).
        assert_eq!(preferred(&scores(134.09, 110.43, 0.38, 0.33), true), Arm);
        // A sound arm and a residual that helps beyond the tolerance.
        assert_eq!(preferred(&scores(9.0, 5.0, 4.0, 1.0), true), ArmResidual);
        // The delta's profile on the PHANToM: arm + residual within 10 % of the vector
        // lattice, but only through its residual lattice.
        assert_eq!(preferred(&scores(67.3, 36.1, 56.6, 39.7), true), Vector);
        // An arm as good as the lattice, within the tolerance, has not failed.
        assert_eq!(preferred(&scores(9.0, 1.0, 1.05, 1.02), true), Arm);
        // A failed arm whose residual still beats the lattice beyond the tolerance is used.
        assert_eq!(preferred(&scores(9.0, 5.0, 6.0, 1.0), true), ArmResidual);
        // No fit to every hold: the lattices only.
        assert_eq!(preferred(&scores(9.0, 5.0, 1.0, 1.0), false), Vector);
    }
}
