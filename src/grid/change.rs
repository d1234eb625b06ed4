//! A payload and a base tilt taken into a grid file (`hgcd check --apply`, docs/calibration.md
//! §2.2): the model is rewritten as if calibrated with the handle and the table as they are now,
//! and `[[applied]]` records what was taken in and when.
//!
//! The rewrite is the model's own compensation of the change
//! ([`crate::control::compensation::GravityModel::with_effect`]), folded into its numbers, so a
//! reader of any version loads the changed model:
//! - a lattice: the payload's weight m_p g v_G added at every vertex (m + m_p along v_G), then
//!   the field turned by the tilt R: v_G' = R v_G, F' = R (F + m_p g v_G);
//! - an arm model: the gravity it is held against turned (v_G' = R v_G), and the payload, a
//!   point mass at the handle, added to the parameters that carry the handle (least squares over
//!   the lattice's vertices: exact where the handle is a point of the last link, as on the
//!   profiles' arms). The lattice beside it changes by what the arm model changes at each vertex,
//!   so the residual the arm leaves there stays as measured.

use nalgebra::{DMatrix, DVector, Rotation3, Vector3};
use serde::{Deserialize, Serialize};

use super::{ArmRecord, GridFile};
use crate::arm::{ArmGravity, MAX_PARAMETERS};

/// What an arm's parameters may leave of a payload's weight at a vertex and still hold it, as a
/// share of the weight: the handle is not a point of the arm's last link.
pub const PAYLOAD_FIT_SHARE: f64 = 0.01;

/// A change of the handle's payload and of the base's tilt, as `hgcd check` measures it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Change {
    /// Mass added to the handle, kg (negative: taken off).
    pub payload_kg: f64,
    /// The base's tilt: the rotation that turns the gravity the model was calibrated under into
    /// the gravity now (rotation vector, device frame, rad).
    pub tilt: Vector3<f64>,
}

/// `[[applied]]`: one change taken into the file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AppliedRecord {
    /// When, UTC.
    pub at: Option<toml::value::Datetime>,
    pub hgcd_version: Option<String>,
    pub payload_g: f64,
    pub tilt_deg: f64,
    /// Unit axis of the tilt (device frame).
    pub tilt_axis: [f64; 3],
    /// Device time of the measurement that found it, s.
    pub device_time_s: Option<f64>,
}

/// Why a change cannot be taken into a grid file.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum ChangeError {
    #[error("the payload or tilt is not a finite number")]
    NotFinite,
    #[error(
        "the arm model cannot carry a payload at the handle: its parameters leave {left_mn:.2} mN \
         of its {weight_mn:.1} mN weight at a vertex (the handle is not a point of its last link); \
         calibrate again with the payload on"
    )]
    PayloadNotInArm { left_mn: f64, weight_mn: f64 },
    #[error("the changed grid is not valid: {0}")]
    Invalid(#[from] super::Problem),
}

impl GridFile {
    /// This file with `change` taken into its model, and `record` appended to `[[applied]]`.
    ///
    /// # Errors
    /// [`ChangeError`]: a number that is not finite, a payload the arm model cannot carry, or a
    /// result outside the format's ranges (a payload heavier than a vertex's range allows).
    pub fn with_change(
        &self,
        change: &Change,
        record: AppliedRecord,
    ) -> Result<GridFile, ChangeError> {
        if !(change.payload_kg.is_finite() && change.tilt.iter().all(|c| c.is_finite())) {
            return Err(ChangeError::NotFinite);
        }
        let turn = Rotation3::new(change.tilt);
        let mut file = self.clone();
        let grid = &mut file.grid;
        let g = grid.g;
        let v = grid.gravity_direction;
        let positions: Vec<Vector3<f64>> = (0..grid.vertex_count())
            .map(|n| {
                let (i, j, k) = grid.coordinates(n);
                grid.vertex_position(i, j, k)
            })
            .collect();
        let arm = match &self.arm {
            Some(record) => Some((record, record.gravity()?)),
            None => None,
        };
        match arm {
            None => {
                // The lattice: F' = R (F + m_p g v_G), v_G' = R v_G.
                for m in grid.masses.iter_mut() {
                    *m += change.payload_kg;
                }
                grid.gravity_direction = turn * v;
                for f in file.vertices.force_vectors.iter_mut() {
                    *f = (turn * (Vector3::from(*f) + v * (change.payload_kg * g))).into();
                }
            }
            Some((record, before)) => {
                let after = changed_arm(&before, change, &positions)?;
                grid.gravity_direction = turn * v;
                let v_after = grid.gravity_direction;
                let vectors = file.vertices.force_vectors.len() == positions.len();
                for (n, x) in positions.iter().enumerate() {
                    let delta = after.force(x) - before.force(x);
                    grid.masses[n] += delta.dot(&v_after) / g;
                    if vectors {
                        let f = &mut file.vertices.force_vectors[n];
                        *f = (Vector3::from(*f) + delta).into();
                    }
                }
                let count = after.arm.parameter_count();
                file.arm = Some(ArmRecord {
                    parameters: after.parameters[..count].to_vec(),
                    gravity_direction: after.up.into(),
                    tilt_deg: after.up.angle(&after.arm.up()).to_degrees(),
                    ..record.clone()
                });
            }
        }
        file.applied.push(record);
        file.check()?;
        Ok(file)
    }
}

/// The arm model `before` under the tilted gravity, carrying the payload at its handle: the
/// parameters' change that holds the payload's weight best over `positions` (least squares,
/// smallest change where the positions leave a direction free).
fn changed_arm(
    before: &ArmGravity,
    change: &Change,
    positions: &[Vector3<f64>],
) -> Result<ArmGravity, ChangeError> {
    let mut after = *before;
    after.up = Rotation3::new(change.tilt) * before.up;
    if change.payload_kg == 0.0 {
        return Ok(after);
    }
    let count = before.arm.parameter_count();
    let weight = after.up * (change.payload_kg * after.g);
    let rows: Vec<_> = positions
        .iter()
        .filter_map(|x| before.arm.force_regressor(x, &after.up, after.g))
        .collect();
    let mut design = DMatrix::zeros(3 * rows.len(), count);
    let mut target = DVector::zeros(3 * rows.len());
    for (r, regressor) in rows.iter().enumerate() {
        for a in 0..3 {
            for p in 0..count {
                design[(3 * r + a, p)] = regressor[(a, p)];
            }
            target[3 * r + a] = weight[a];
        }
    }
    let delta = design
        .clone()
        .svd(true, true)
        .solve(&target, 1e-12)
        .unwrap_or_else(|_| DVector::zeros(count));
    let left = (&design * &delta - &target)
        .as_slice()
        .chunks(3)
        .map(|c| Vector3::new(c[0], c[1], c[2]).norm())
        .fold(0.0, f64::max);
    if rows.is_empty() || left > PAYLOAD_FIT_SHARE * weight.norm() {
        return Err(ChangeError::PayloadNotInArm {
            left_mn: left * 1e3,
            weight_mn: weight.norm() * 1e3,
        });
    }
    for p in 0..count.min(MAX_PARAMETERS) {
        after.parameters[p] += delta[p];
    }
    Ok(after)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::file::tests::calibrated;

    /// Folded into a file, the change compensates as `hgcd check` fitted it: tested against the
    /// effect in `control::compensation`'s tests.
    #[test]
    fn a_change_that_is_not_a_number_is_refused() {
        let change = Change {
            payload_kg: f64::NAN,
            tilt: Vector3::zeros(),
        };
        let record = AppliedRecord {
            at: None,
            hgcd_version: None,
            payload_g: f64::NAN,
            tilt_deg: 0.0,
            tilt_axis: [1.0, 0.0, 0.0],
            device_time_s: None,
        };
        assert_eq!(
            calibrated().with_change(&change, record),
            Err(ChangeError::NotFinite)
        );
    }
}
