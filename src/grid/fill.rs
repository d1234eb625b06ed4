//! Filling a lattice's unknown vertices from their neighbours: an unreachable vertex of a
//! calibrated grid, an explored grid's outer vertices, and a held-out hold's value predicted from
//! the others (`fit`).

/// Fill the vertices of a `dims` grid (x fastest) whose `known` flag is false from their face
/// neighbours: each round gives every unfilled vertex with at least one filled neighbour the mean
/// of those neighbours' values (from the rounds before), until all are filled. Requires at least
/// one known vertex.
pub fn fill_from_neighbours<T: Field>(dims: [usize; 3], values: &mut [T], known: &[bool]) {
    fill_in_rounds(dims, values, known, false);
}

/// Like [`fill_from_neighbours`], but along each direction where the neighbour beyond the filled
/// neighbour is filled too, the candidate is their straight line carried on (2 v₁ − v₂) rather
/// than v₁: an explored grid's outer vertices continue the field's trend, and the interpolation
/// between them and the calibrated ones has no step at the edge of what was measured.
pub fn extrapolate_from_neighbours<T: Field>(dims: [usize; 3], values: &mut [T], known: &[bool]) {
    fill_in_rounds(dims, values, known, true);
}

/// What a vertex holds that filling can average: forces, friction, numbers.
pub trait Field: Copy + std::ops::Add<Output = Self> + std::ops::Mul<f64, Output = Self> {}
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
