//! What a calibration ends with: a [`CalibrationResult`] or a [`CalibrationFailure`]; and the
//! two things worked out once every vertex is measured: v_G from the whole field, and the
//! values of vertices the handle could not reach, filled from their neighbours.

use nalgebra::{Matrix3, SymmetricEigen, Vector3};

use super::plan::Vertex;

/// What was measured at one vertex (or, for one the handle could not reach, filled in).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VertexResult {
    pub vertex: Vertex,
    /// Apparent mass M̂(X_i) = F·v_G / g, kg: negative where the force points along −v_G.
    pub mass: f64,
    /// Holding force: the middle of the stick band, N (what the vector mode interpolates).
    pub force: Vector3<f64>,
    /// The force at the first rest near the vertex, N: the one-sided measurement the paper's
    /// procedure makes, anywhere inside the stick band (reported beside `force`).
    pub one_sided_force: Vector3<f64>,
    /// Half-width of the stick band along x, y and z: the friction there, N.
    pub friction: Vector3<f64>,
    /// Updates of the force estimate (settles off the vertex and rounds of band measurements).
    pub iterations: u32,
    /// Distance from the vertex of the rest the band was measured at, m.
    pub final_error: f64,
    /// Where `force` was measured, m: the second rest near the vertex without friction, the mean
    /// of the rests the bands were crossed from with it. The result carries `force` from there
    /// to the vertex (`carry_to_vertices`).
    pub measured_at: Vector3<f64>,
    /// Device time spent on this vertex, move included, s.
    pub duration: f64,
    /// False for a vertex the handle could not reach: its values are filled from neighbours.
    pub reached: bool,
}

/// What the initialisation measured at the rest point X_C.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct InitialMeasurement {
    /// Holding force at X_C (the middle of the stick bands), N; where the survey strokes found
    /// the bands misread, the holding force the strokes measured.
    pub load: Vector3<f64>,
    /// Half-widths of the stick bands along x, y, z, N; where the bands were misread, the
    /// sliding friction the survey strokes measured along each axis.
    pub friction: Vector3<f64>,
    /// Moving mass along x, y, z, kg.
    pub inertia: Vector3<f64>,
    /// Standard deviation of the reported position at rest, m.
    pub noise: f64,
    /// The largest step between consecutive readings at rest: the encoder's step, or a few
    /// standard deviations of noise without one, m.
    pub step: f64,
    /// Hold stiffness built from these, N/m per axis.
    pub stiffness: Vector3<f64>,
}

/// A finished calibration.
#[derive(Clone, Debug, PartialEq)]
pub struct CalibrationResult {
    /// Unit v_G: the principal direction of the measured holding forces, signed so that the
    /// masses are positive on average.
    pub gravity_direction: Vector3<f64>,
    /// |load| / g at X_C, kg: a rough mass.
    pub initial_mass: f64,
    /// Rest point X_C of the initialisation, m.
    pub rest_point: Vector3<f64>,
    pub initial: InitialMeasurement,
    /// Results in grid order (x fastest).
    pub vertices: Vec<VertexResult>,
    pub origin: Vector3<f64>,
    pub dims: [usize; 3],
    pub left_out: Vec<Vertex>,
    /// Vertices the handle could not reach (their values are filled, `docs/grid-format.md` §4).
    pub unreachable: Vec<Vertex>,
    /// Vertices of an explored grid outside the explored workspace: never visited, their values
    /// extrapolated from the calibrated ones (`docs/grid-format.md` §4).
    pub extrapolated: Vec<Vertex>,
    /// What exploration found (`calibration.workspace = "explore"`).
    pub workspace: Option<super::explore::WorkspaceMap>,
    /// Device time of the whole run, s.
    pub duration: f64,
}

/// Why a calibration failed.
#[derive(Clone, Copy, Debug, PartialEq, thiserror::Error)]
pub enum CalibrationFailure {
    #[error(
        "initialisation found no steady state within {timeout:.0} s (is the handle free to move \
         and held by nothing but the field?)"
    )]
    InitTimeout { timeout: f64 },
    #[error(
        "initialisation: the handle did not move under {push_n:.2} N along {axis}; something holds \
         it (a hand, a cable, a support), or its friction is beyond what calibration pushes \
         (a quarter of safety.max_force_n)"
    )]
    Held { axis: char, push_n: f64 },
    #[error(
        "{vertex} did not converge within {timeout:.0} s ({iterations} updates); the handle may \
         be blocked by a stop, the vertex may lie outside the reachable workspace, or \
         calibration.eps_m_mm may be below the position noise"
    )]
    VertexTimeout {
        vertex: Vertex,
        timeout: f64,
        iterations: u32,
    },
    #[error("{vertex} did not converge after {iterations} updates")]
    TooManyIterations { vertex: Vertex, iterations: u32 },
    #[error(
        "the handle reached none of the {count} vertices (mechanical stops or obstacles? check \
         device.workspace_*_mm and calibration.centre_mm)"
    )]
    NothingReached { count: usize },
    #[error(
        "the explored workspace spans {needed} vertices along {axis} at calibration.spacing_mm; \
         at most {} fit (raise calibration.spacing_mm)",
        super::plan::MAX_EXPLORED_SIDE
    )]
    ExploredTooLarge { axis: char, needed: usize },
    #[error(
        "exploration found no vertex {margin_mm:.0} mm inside the reachable workspace (the \
         handle met stops close to X_C along every direction: is it free to move?)"
    )]
    NothingExplored { margin_mm: f64 },
}

/// v_G from the measured holding forces: the unit v maximising Σ (F·v)² (the direction a scalar
/// field M g v_G best represents them along), signed so that Σ F·v ≥ 0. None without any force.
pub(super) fn principal_direction(
    forces: impl Iterator<Item = Vector3<f64>>,
) -> Option<Vector3<f64>> {
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
pub(super) fn carry_to_vertices(
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

/// Fill the vertices of a `dims` grid (x fastest) whose `known` flag is false from their face
/// neighbours: each round gives every unfilled vertex with at least one filled neighbour the mean
/// of those neighbours' values (from the rounds before), until all are filled. Requires at least
/// one known vertex.
pub(super) fn fill_from_neighbours<T: Field>(dims: [usize; 3], values: &mut [T], known: &[bool]) {
    fill_in_rounds(dims, values, known, false);
}

/// Like [`fill_from_neighbours`], but along each direction where the neighbour beyond the filled
/// neighbour is filled too, the candidate is their straight line carried on (2 v₁ − v₂) rather
/// than v₁: an explored grid's outer vertices continue the field's trend, and the interpolation
/// between them and the calibrated ones has no step at the edge of what was measured.
pub(crate) fn extrapolate_from_neighbours<T: Field>(
    dims: [usize; 3],
    values: &mut [T],
    known: &[bool],
) {
    fill_in_rounds(dims, values, known, true);
}

/// What a vertex holds that filling can average: forces, friction, numbers.
pub(crate) trait Field:
    Copy + std::ops::Add<Output = Self> + std::ops::Mul<f64, Output = Self>
{
}
impl<T: Copy + std::ops::Add<Output = T> + std::ops::Mul<f64, Output = T>> Field for T {}

fn fill_in_rounds<T: Field>(dims: [usize; 3], values: &mut [T], known: &[bool], linear: bool) {
    let mut filled = known.to_vec();
    let index = |c: [usize; 3]| c[0] + dims[0] * (c[1] + dims[1] * c[2]);
    // The vertex `steps` along axis `a` from `c`, if inside the grid.
    let along = |c: [usize; 3], a: usize, steps: i64| {
        let v = c[a] as i64 + steps;
        (v >= 0 && v < dims[a] as i64).then(|| {
            let mut m = c;
            m[a] = v as usize;
            index(m)
        })
    };
    while filled.iter().any(|f| !f) {
        let before = filled.clone();
        let mut any = false;
        for k in 0..dims[2] {
            for j in 0..dims[1] {
                for i in 0..dims[0] {
                    let c = [i, j, k];
                    let n = index(c);
                    if before[n] {
                        continue;
                    }
                    let mut candidates = Vec::with_capacity(6);
                    for a in 0..3 {
                        for step in [-1i64, 1] {
                            let Some(first) = along(c, a, step).filter(|&m| before[m]) else {
                                continue;
                            };
                            let beyond = along(c, a, 2 * step).filter(|&m| before[m] && linear);
                            candidates.push(match beyond {
                                Some(second) => values[first] * 2.0 + values[second] * -1.0,
                                None => values[first],
                            });
                        }
                    }
                    if let Some((&first, rest)) = candidates.split_first() {
                        let sum = rest.iter().fold(first, |acc, &v| acc + v);
                        values[n] = sum * (1.0 / candidates.len() as f64);
                        filled[n] = true;
                        any = true;
                    }
                }
            }
        }
        assert!(any, "filling a grid needs at least one known vertex");
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

    #[test]
    fn extrapolated_vertices_carry_on_a_linear_field() {
        // A row known at its first three vertices of a field 1 + 2x: the last two continue it.
        let mut row = [1.0, 3.0, 5.0, 0.0, 0.0];
        extrapolate_from_neighbours([5, 1, 1], &mut row, &[true, true, true, false, false]);
        assert_eq!(row, [1.0, 3.0, 5.0, 7.0, 9.0]);
        // A 4×4 layer of 1 + x + 3y known only on its inner 2×2: every vertex comes out exact.
        let f = |i: usize, j: usize| 1.0 + i as f64 + 3.0 * j as f64;
        let mut layer = [0.0; 16];
        let mut known = [false; 16];
        for (i, j) in [(1, 1), (2, 1), (1, 2), (2, 2)] {
            layer[i + 4 * j] = f(i, j);
            known[i + 4 * j] = true;
        }
        extrapolate_from_neighbours([4, 4, 1], &mut layer, &known);
        for j in 0..4 {
            for i in 0..4 {
                assert!(
                    (layer[i + 4 * j] - f(i, j)).abs() < 1e-12,
                    "({i}, {j}): {layer:?}"
                );
            }
        }
    }

    #[test]
    fn unreachable_vertices_take_the_mean_of_their_filled_neighbours() {
        // A 3×1×1 row with only its first vertex known, and a 3×3×1 layer with a missing
        // corner and centre.
        let mut row = [2.0, 0.0, 0.0];
        fill_from_neighbours([3, 1, 1], &mut row, &[true, false, false]);
        assert_eq!(row, [2.0, 2.0, 2.0]);
        let mut layer = [1.0, 2.0, 3.0, 4.0, 0.0, 6.0, 7.0, 8.0, 0.0];
        let known = [true, true, true, true, false, true, true, true, false];
        fill_from_neighbours([3, 3, 1], &mut layer, &known);
        // Centre: mean of 2, 4, 6, 8; the corner (2, 2): mean of 6 and 8 (the centre was not
        // yet filled in that round).
        assert_eq!(layer[4], 5.0);
        assert_eq!(layer[8], 7.0);
    }
}
