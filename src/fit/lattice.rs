//! The lattice's share of a calibration: from the holds measured at the vertices the handle
//! reached, each hold carried from where it was measured to its vertex, the vertices not reached
//! filled from their neighbours, and v_G, the direction of the paper's scalar field.
//! `control::calibration` measures; this completes the grid both lattices interpolate.

use nalgebra::{Matrix3, SymmetricEigen, Vector3};

use crate::grid::{extrapolate_from_neighbours, fill_from_neighbours};

/// What a `dims` grid (x fastest) holds at each vertex, measured where `known` and to be filled
/// elsewhere.
pub struct VertexFields<'a> {
    pub known: &'a [bool],
    /// Each vertex's position less where its hold was measured, m.
    pub offsets: &'a [Vector3<f64>],
    /// The holding forces (the middle of the stick band), N.
    pub forces: &'a mut [Vector3<f64>],
    /// The one-sided forces of the paper's procedure, N.
    pub one_sided: &'a mut [Vector3<f64>],
    /// The friction (the band's half-width along x, y and z), N.
    pub friction: &'a mut [Vector3<f64>],
}

/// Complete the `dims` grid of cube side `spacing` (m): the holding forces carried to their
/// vertices ([`carry_to_vertices`]), the vertices not known filled from their neighbours, linearly
/// (the field's trend carried on) for an `explored` grid, whose outer vertices lie beyond what was
/// reached; friction is always filled. Returns v_G: the principal direction of the known forces,
/// else along `load` (the force that held the handle at the start), else z.
pub fn complete(
    dims: [usize; 3],
    spacing: f64,
    explored: bool,
    load: Vector3<f64>,
    fields: VertexFields,
) -> Vector3<f64> {
    let known = fields.known;
    let gravity_direction = principal_direction(
        fields
            .forces
            .iter()
            .zip(known)
            .filter(|(_, &k)| k)
            .map(|(f, _)| *f),
    )
    .or_else(|| (load.norm() > 0.0).then(|| load.normalize()))
    .unwrap_or_else(Vector3::z);
    carry_to_vertices(dims, spacing, fields.forces, fields.offsets, known);
    let fill_forces = if explored {
        extrapolate_from_neighbours::<Vector3<f64>>
    } else {
        fill_from_neighbours::<Vector3<f64>>
    };
    fill_forces(dims, fields.forces, known);
    fill_forces(dims, fields.one_sided, known);
    fill_from_neighbours(dims, fields.friction, known);
    gravity_direction
}

/// v_G from the measured holding forces: the unit v maximising Σ (F·v)² (the direction a scalar
/// field M g v_G best represents them along), signed so that Σ F·v ≥ 0. None without any force.
pub fn principal_direction(forces: impl Iterator<Item = Vector3<f64>>) -> Option<Vector3<f64>> {
    let (mut scatter, mut sum) = (Matrix3::zeros(), Vector3::zeros());
    for f in forces {
        scatter += f * f.transpose();
        sum += f;
    }
    let eigen = SymmetricEigen::new(scatter);
    let (k, largest) = eigen
        .eigenvalues
        .iter()
        .enumerate()
        .fold(
            (0, f64::MIN),
            |best, (k, &l)| if l > best.1 { (k, l) } else { best },
        );
    if largest <= 0.0 {
        return None;
    }
    let v: Vector3<f64> = eigen.eigenvectors.column(k).into();
    Some(if v.dot(&sum) < 0.0 { -v } else { v })
}

/// Carry the forces of the `known` vertices of a `dims` grid (x fastest, cube side `spacing`)
/// from where they were measured to the vertices: F(X_i) ≈ F(X̄_i) + ∇F (X_i − X̄_i), with
/// `offsets` the X_i − X̄_i. The holding force of a linkage changes by up to some 20 N/m over its
/// workspace, and the slips of the band measurements leave the handle up to a millimetre or two
/// from the vertex. The gradient comes from the measured forces along each axis of the grid:
/// central differences inside, second-order one-sided ones at its faces, first-order ones with
/// only two known vertices on the line, none with fewer.
pub fn carry_to_vertices(
    dims: [usize; 3],
    spacing: f64,
    forces: &mut [Vector3<f64>],
    offsets: &[Vector3<f64>],
    known: &[bool],
) {
    let measured = forces.to_vec();
    let stride = [1, dims[0], dims[0] * dims[1]];
    for n in (0..forces.len()).filter(|&n| known[n]) {
        let mut carried = Vector3::zeros();
        for a in 0..3 {
            let p = (n / stride[a]) % dims[a];
            // The known force `step` vertices along axis a from this one.
            let at = |step: isize| {
                let q = p as isize + step;
                (q >= 0 && (q as usize) < dims[a])
                    .then(|| (n as isize + step * stride[a] as isize) as usize)
                    .filter(|&m| known[m])
                    .map(|m| measured[m])
            };
            let f = measured[n];
            let gradient = match (at(-2), at(-1), at(1), at(2)) {
                (_, Some(before), Some(after), _) => (after - before) / (2.0 * spacing),
                (_, None, Some(after), Some(next)) => {
                    (4.0 * after - 3.0 * f - next) / (2.0 * spacing)
                }
                (Some(next), Some(before), None, _) => {
                    (3.0 * f - 4.0 * before + next) / (2.0 * spacing)
                }
                (_, None, Some(after), None) => (after - f) / spacing,
                (None, Some(before), None, _) => (f - before) / spacing,
                _ => Vector3::zeros(),
            };
            carried += gradient * offsets[n][a];
        }
        forces[n] += carried;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn v_g_is_the_principal_direction_signed_to_the_mean_force() {
        let up = Vector3::new(0.1, -0.2, 1.0).normalize();
        // A field that changes sign along v_G (an over-balanced region) still gives v_G.
        let forces = [up * 1.2, up * -0.3, up * 0.01, up * 2.0];
        let v = principal_direction(forces.into_iter()).unwrap();
        assert!((v - up).norm() < 1e-12, "{v}");
        // All along −up: v_G points along the forces (the masses come out positive).
        let v = principal_direction(forces.iter().map(|f| -f)).unwrap();
        assert!((v + up).norm() < 1e-12, "{v}");
        assert_eq!(principal_direction(std::iter::empty()), None);
    }
}
