//! The lattice the hot path uses: apparent masses at the vertices of a cubic lattice and trilinear
//! interpolation between them. No I/O here; the file format is in `file.rs`.

use std::ops::RangeInclusive;

use nalgebra::Vector3;

use super::Problem;

/// Gravitational accelerations a grid may be relative to, m/s²: Earth's 9.81 within about 2.
pub const G_RANGE: RangeInclusive<f64> = 8.0..=12.0;
/// Cube sides a grid may have, m: 1 mm to 0.5 m.
pub const SPACING_RANGE: RangeInclusive<f64> = 1e-3..=0.5;
/// Largest magnitude of an apparent mass, kg (far beyond any haptic handle).
pub const MAX_MASS_KG: f64 = 100.0;
/// Largest magnitude of a coordinate of the grid's origin, m.
pub const MAX_ORIGIN_M: f64 = 10.0;
/// Vertices along one axis: 1 to 1000.
pub const DIM_RANGE: RangeInclusive<i64> = 1..=1000;
/// Largest number of vertices a grid may hold (keeps hostile files from exhausting memory).
pub const MAX_VERTICES: usize = 1_000_000;
/// How far a gravity direction's norm may stray from 1.
pub const UNIT_TOLERANCE: f64 = 1e-3;

/// Apparent mass M(X) sampled on a cubic lattice, with the gravity direction it was measured along.
#[derive(Clone, Debug, PartialEq)]
pub struct MassGrid {
    /// Gravitational acceleration the masses are relative to, m/s².
    pub g: f64,
    /// Unit v_G: the direction of the compensating force (opposite to gravity).
    pub gravity_direction: Vector3<f64>,
    /// Position of the vertex with the smallest coordinates, m.
    pub origin: Vector3<f64>,
    /// Cube side L, m.
    pub spacing: f64,
    /// Vertices along x, y, z.
    pub dims: [usize; 3],
    /// Apparent mass at each vertex, kg, x fastest: index i + nx·(j + ny·k).
    pub masses: Vec<f64>,
}

/// Trilinear weights of the eight vertices of one cell: (vertex indices, weights).
pub type CellWeights = ([usize; 8], [f64; 8]);

impl MassGrid {
    /// A grid with the same mass everywhere (useful as a simulator field or a first guess).
    pub fn uniform(
        mass: f64,
        g: f64,
        gravity_direction: Vector3<f64>,
        origin: Vector3<f64>,
        spacing: f64,
        dims: [usize; 3],
    ) -> Self {
        let n = dims.iter().product();
        Self {
            g,
            gravity_direction: gravity_direction.normalize(),
            origin,
            spacing,
            dims,
            masses: vec![mass; n],
        }
    }

    /// The same lattice with vertex (i, j, k) given the mass `mass(i, j, k)`, kg.
    pub fn with_masses(mut self, mass: impl Fn(usize, usize, usize) -> f64) -> Self {
        let [ni, nj, nk] = self.dims;
        for k in 0..nk {
            for j in 0..nj {
                for i in 0..ni {
                    let n = self.index(i, j, k);
                    self.masses[n] = mass(i, j, k);
                }
            }
        }
        self
    }

    /// Number of vertices.
    pub fn vertex_count(&self) -> usize {
        self.masses.len()
    }

    /// Flat index of vertex (i, j, k).
    pub fn index(&self, i: usize, j: usize, k: usize) -> usize {
        i + self.dims[0] * (j + self.dims[1] * k)
    }

    /// (i, j, k) of the vertex at flat index `n`.
    pub fn coordinates(&self, n: usize) -> (usize, usize, usize) {
        (
            n % self.dims[0],
            (n / self.dims[0]) % self.dims[1],
            n / (self.dims[0] * self.dims[1]),
        )
    }

    /// Position of vertex (i, j, k), m.
    pub fn vertex_position(&self, i: usize, j: usize, k: usize) -> Vector3<f64> {
        self.origin + Vector3::new(i as f64, j as f64, k as f64) * self.spacing
    }

    /// Position of the vertex with the largest coordinates, m.
    pub fn far_corner(&self) -> Vector3<f64> {
        self.vertex_position(self.dims[0] - 1, self.dims[1] - 1, self.dims[2] - 1)
    }

    /// Whether `x` lies inside the grid's bounding box (faces included).
    pub fn contains(&self, x: &Vector3<f64>) -> bool {
        let far = self.far_corner();
        (0..3).all(|a| x[a] >= self.origin[a] && x[a] <= far[a])
    }

    /// How far `x` lies outside the grid's bounding box, m (0 inside).
    pub fn distance_outside(&self, x: &Vector3<f64>) -> f64 {
        let far = self.far_corner();
        ((self.origin - x).sup(&Vector3::zeros()) + (x - far).sup(&Vector3::zeros())).norm()
    }

    /// Trilinear weights for `x`. Outside the grid the position is clamped onto it, so the nearest
    /// cell's face values hold. Coefficients are normalised: b = (x − x_k)/L, a = 1 − b (the paper's
    /// Section 4 writes (L − b)/L, which mixes units).
    pub fn cell_weights(&self, x: &Vector3<f64>) -> CellWeights {
        // Index arithmetic wraps explicitly: a checked grid holds at most `MAX_VERTICES`, so
        // nothing here can overflow, and the release profile's overflow checks would otherwise
        // guard every one of the 8 vertices' indices on the servo thread.
        let mut first = 0usize; // flat index of the cell's vertex 0
        let mut stride = 1usize;
        let mut next = [0usize; 3]; // flat step to the next vertex along each axis (0: flat)
        let mut frac = [0f64; 3];
        for a in 0..3 {
            let n = self.dims[a];
            if n > 1 {
                let cells = n.wrapping_sub(1);
                let u = ((x[a] - self.origin[a]) / self.spacing).clamp(0.0, cells as f64);
                let cell = (u.floor() as usize).min(cells.wrapping_sub(1));
                first = first.wrapping_add(cell.wrapping_mul(stride));
                frac[a] = u - cell as f64;
                next[a] = stride;
            }
            stride = stride.wrapping_mul(n);
        }
        let (b, d, f) = (frac[0], frac[1], frac[2]);
        let (a, c, e) = (1.0 - b, 1.0 - d, 1.0 - f);
        let mut idx = [0usize; 8];
        let mut w = [0f64; 8];
        // Vertex n has offsets (n & 1, (n >> 1) & 1, (n >> 2) & 1): the paper's M_0 … M_7.
        for n in 0..8 {
            let (ox, oy, oz) = (n & 1, (n >> 1) & 1, (n >> 2) & 1);
            idx[n] = first
                .wrapping_add(ox * next[0])
                .wrapping_add(oy * next[1])
                .wrapping_add(oz * next[2]);
            w[n] = [a, b][ox] * [c, d][oy] * [e, f][oz];
        }
        (idx, w)
    }

    /// Apparent mass at `x`, kg, trilinearly interpolated (nearest cell held outside the grid).
    pub fn mass_at(&self, x: &Vector3<f64>) -> f64 {
        let (idx, w) = self.cell_weights(x);
        (0..8).map(|n| w[n] * self.masses[idx[n]]).sum()
    }

    /// Compensating force M(X) g v_G at `x`, N.
    pub fn gravity_force(&self, x: &Vector3<f64>) -> Vector3<f64> {
        self.gravity_direction * (self.mass_at(x) * self.g)
    }

    /// Check every number against its range (`docs/grid-format.md` §3), in the order the keys are
    /// listed there. A grid that passes interpolates to finite masses and forces everywhere.
    pub fn check(&self) -> Result<(), Problem> {
        in_range("g", self.g, &G_RANGE, "m/s²")?;
        let norm = self.gravity_direction.norm();
        if !norm.is_finite() || (norm - 1.0).abs() > UNIT_TOLERANCE {
            return Err(Problem::NotUnit { norm });
        }
        for c in self.origin.iter() {
            in_range("origin", *c, &(-MAX_ORIGIN_M..=MAX_ORIGIN_M), "m")?;
        }
        in_range("spacing", self.spacing, &SPACING_RANGE, "m")?;
        for &n in &self.dims {
            if !DIM_RANGE.contains(&(n as i64)) {
                return Err(Problem::Dims { value: n as i64 });
            }
        }
        let need = self.dims.iter().map(|&n| n as u64).product::<u64>();
        if need > MAX_VERTICES as u64 {
            return Err(Problem::TooManyVertices { count: need });
        }
        if self.masses.len() as u64 != need {
            return Err(Problem::MassCount {
                len: self.masses.len(),
                dims: self.dims,
                need,
            });
        }
        for (vertex, &value) in self.masses.iter().enumerate() {
            // Any sign: an over-balanced linkage has a negative apparent mass, and one balanced
            // at a vertex a zero one (docs/grid-format.md §3 #11).
            if !(value.is_finite() && value.abs() <= MAX_MASS_KG) {
                return Err(Problem::Mass { vertex, value });
            }
        }
        Ok(())
    }
}

fn in_range(
    key: &'static str,
    value: f64,
    range: &RangeInclusive<f64>,
    unit: &'static str,
) -> Result<(), Problem> {
    if range.contains(&value) {
        Ok(())
    } else {
        Err(Problem::OutOfRange {
            key,
            value,
            min: *range.start(),
            max: *range.end(),
            unit,
        })
    }
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;

    pub(crate) fn sample() -> MassGrid {
        MassGrid::uniform(
            0.1,
            9.81,
            Vector3::z(),
            Vector3::new(-0.04, -0.04, -0.04),
            0.04,
            [3, 3, 3],
        )
        .with_masses(|i, j, k| 0.05 + 0.01 * i as f64 + 0.02 * j as f64 + 0.04 * k as f64)
    }

    #[test]
    fn interpolation_hits_vertices_and_is_exact_for_affine_fields() {
        let g = sample();
        for k in 0..3 {
            for j in 0..3 {
                for i in 0..3 {
                    let x = g.vertex_position(i, j, k);
                    assert!((g.mass_at(&x) - g.masses[g.index(i, j, k)]).abs() < 1e-12);
                }
            }
        }
        // The field is affine in (i, j, k), so trilinear interpolation reproduces it everywhere.
        let x = Vector3::new(0.013, -0.027, 0.031);
        let u = (x - g.origin) / g.spacing;
        let expected = 0.05 + 0.01 * u.x + 0.02 * u.y + 0.04 * u.z;
        assert!((g.mass_at(&x) - expected).abs() < 1e-12);
    }

    #[test]
    fn interpolation_matches_the_paper_formula_in_one_cell() {
        let mut g = sample();
        // Make the field non-affine so the cross terms matter.
        for (n, m) in g.masses.iter_mut().enumerate() {
            *m = 0.05 + ((n * 7919) % 23) as f64 * 0.01;
        }
        let x = Vector3::new(0.011, 0.002, -0.035);
        let (xk, yk, zk) = (0.0, 0.0, -0.04);
        let l = 0.04;
        let (b, d, f) = ((x.x - xk) / l, (x.y - yk) / l, (x.z - zk) / l);
        let (a, c, e) = (1.0 - b, 1.0 - d, 1.0 - f);
        let m = |i, j, k| g.masses[g.index(i, j, k)];
        let expected = e * c * a * m(1, 1, 0)
            + e * c * b * m(2, 1, 0)
            + e * d * a * m(1, 2, 0)
            + e * d * b * m(2, 2, 0)
            + f * c * a * m(1, 1, 1)
            + f * c * b * m(2, 1, 1)
            + f * d * a * m(1, 2, 1)
            + f * d * b * m(2, 2, 1);
        assert!((g.mass_at(&x) - expected).abs() < 1e-12);
    }

    #[test]
    fn outside_the_grid_the_nearest_face_holds() {
        let g = sample();
        let inside = Vector3::new(0.04, 0.01, -0.02);
        let outside = Vector3::new(0.09, 0.01, -0.02);
        assert!((g.mass_at(&inside) - g.mass_at(&outside)).abs() < 1e-12);
    }

    #[test]
    fn numbers_outside_their_physical_range_are_named() {
        assert_eq!(sample().check(), Ok(()));
        let out_of_range = |key, value| move |p: Problem| matches!(p, Problem::OutOfRange { key: k, value: v, .. } if k == key && v.to_bits() == f64::to_bits(value));
        let mut g = sample();
        g.g = 1e308;
        assert!(out_of_range("g", 1e308)(g.check().unwrap_err()));
        g.g = 1.62; // the Moon's
        assert!(out_of_range("g", 1.62)(g.check().unwrap_err()));
        let mut g = sample();
        g.spacing = 1e-4;
        assert!(out_of_range("spacing", 1e-4)(g.check().unwrap_err()));
        g.spacing = 2.0;
        assert!(out_of_range("spacing", 2.0)(g.check().unwrap_err()));
        let mut g = sample();
        g.origin.y = -1e9;
        assert!(out_of_range("origin", -1e9)(g.check().unwrap_err()));
        for bad in [
            1e300,
            -1e300,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NAN,
            -100.001,
        ] {
            let mut g = sample();
            g.masses[4] = bad;
            assert!(
                matches!(g.check(), Err(Problem::Mass { vertex: 4, .. })),
                "{bad}"
            );
        }
        // The sign rule changed deliberately (issue 17): an over-balanced arm has a negative
        // apparent mass (the PHANToM 1.5 about −8 g at home), and one balanced at a vertex a zero
        // one. Any finite mass up to the magnitude bound passes, of either sign.
        let mut g = sample();
        g.masses[3] = -0.008;
        g.masses[4] = 0.0;
        g.masses[5] = MAX_MASS_KG;
        g.masses[6] = -MAX_MASS_KG;
        g.masses[7] = -1e-9;
        assert_eq!(g.check(), Ok(()));
        // It interpolates like any other: the force points along −v_G where M < 0.
        let x = g.vertex_position(0, 1, 0);
        assert!((g.gravity_force(&x) - Vector3::new(0.0, 0.0, -0.008 * 9.81)).norm() < 1e-12);
    }
}
