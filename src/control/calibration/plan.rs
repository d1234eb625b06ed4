//! The grid to calibrate: the vertices (nL, mL, pL) + centre with n, m, p ∈ [−N, N], the ones
//! left out, and the order they are visited in.
//!
//! A vertex outside the workspace box is left out together with every vertex on its index plane,
//! so the vertices kept form a rectangular sub-grid (at least 2 along each axis). They are visited
//! along a serpentine path, so the previous vertex is always a neighbour (Eq. 12 starts each
//! vertex from the mass of the closest previous one).

use nalgebra::Vector3;

use super::CalibrationParams;

/// One grid vertex: its paper indices (n, m, p) ∈ [−N, N]³ and its position.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Vertex {
    pub index: [i32; 3],
    pub position: Vector3<f64>,
}

impl std::fmt::Display for Vertex {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let p = self.position * 1e3;
        write!(
            f,
            "vertex ({}, {}, {}) at ({:.1}, {:.1}, {:.1}) mm",
            self.index[0], self.index[1], self.index[2], p.x, p.y, p.z
        )
    }
}

/// The vertices to visit, in serpentine order, and the grid they form.
#[derive(Clone, Debug, PartialEq)]
pub struct GridPlan {
    /// Vertices in visiting order.
    pub path: Vec<Vertex>,
    /// For each vertex of `path`, its flat index in the grid (x fastest).
    pub grid_index: Vec<usize>,
    /// Smallest-coordinate vertex, m.
    pub origin: Vector3<f64>,
    pub dims: [usize; 3],
    /// Vertices outside the workspace, left out.
    pub left_out: Vec<Vertex>,
}

/// Why a grid cannot be planned.
#[derive(Debug, PartialEq, thiserror::Error)]
pub enum PlanError {
    #[error(
        "only {inside} of {total} vertices along {axis} lie inside the workspace; at least 2 are \
         needed (move calibration.centre_mm, shrink calibration.spacing_mm or check \
         device.workspace_*_mm)"
    )]
    TooFewInside {
        axis: char,
        inside: usize,
        total: usize,
    },
    #[error("calibration's velocity filter cannot be built: {0} (check [estimate])")]
    Filter(#[source] crate::estimate::FoawError),
}

impl GridPlan {
    /// The vertex with the largest coordinates, m.
    pub fn far_corner(&self) -> Vector3<f64> {
        let last = |a: usize| {
            self.path
                .iter()
                .map(|v| v.position[a])
                .fold(f64::MIN, f64::max)
        };
        Vector3::new(last(0), last(1), last(2))
    }

    /// Vertices (nL, mL, pL) + centre, n, m, p ∈ [−N, N], keeping those inside the workspace box
    /// (for a box, the kept ones form a rectangular sub-grid).
    pub fn new(params: &CalibrationParams) -> Result<Self, PlanError> {
        let n = params.half_size as i32;
        let (lo, hi) = params.workspace;
        let mut kept: [Vec<i32>; 3] = Default::default();
        for axis in 0..3 {
            for k in -n..=n {
                let x = params.centre[axis] + f64::from(k) * params.spacing;
                if x >= lo[axis] - 1e-12 && x <= hi[axis] + 1e-12 {
                    kept[axis].push(k);
                }
            }
            if kept[axis].len() < 2 {
                return Err(PlanError::TooFewInside {
                    axis: ['x', 'y', 'z'][axis],
                    inside: kept[axis].len(),
                    total: (2 * n + 1) as usize,
                });
            }
        }
        let at = |k: [i32; 3]| {
            params.centre
                + Vector3::new(f64::from(k[0]), f64::from(k[1]), f64::from(k[2])) * params.spacing
        };
        let mut left_out = Vec::new();
        for p in -n..=n {
            for m in -n..=n {
                for q in -n..=n {
                    let k = [q, m, p];
                    if (0..3).any(|a| !kept[a].contains(&k[a])) {
                        left_out.push(Vertex {
                            index: k,
                            position: at(k),
                        });
                    }
                }
            }
        }
        let dims = [kept[0].len(), kept[1].len(), kept[2].len()];
        let mut path = Vec::with_capacity(dims.iter().product());
        let mut grid_index = Vec::with_capacity(path.capacity());
        // Serpentine: x sweeps alternate per row, rows alternate per layer.
        let mut row = 0usize;
        for (kz, &p) in kept[2].iter().enumerate() {
            let ys: Vec<usize> = if kz % 2 == 0 {
                (0..dims[1]).collect()
            } else {
                (0..dims[1]).rev().collect()
            };
            for jy in ys {
                let xs: Vec<usize> = if row % 2 == 0 {
                    (0..dims[0]).collect()
                } else {
                    (0..dims[0]).rev().collect()
                };
                row += 1;
                for ix in xs {
                    let k = [kept[0][ix], kept[1][jy], p];
                    path.push(Vertex {
                        index: k,
                        position: at(k),
                    });
                    grid_index.push(ix + dims[0] * (jy + dims[1] * kz));
                }
            }
        }
        Ok(Self {
            origin: at([kept[0][0], kept[1][0], kept[2][0]]),
            path,
            grid_index,
            dims,
            left_out,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Config;

    fn params() -> CalibrationParams {
        CalibrationParams::from_config(&Config::default())
    }

    #[test]
    fn paper_grid_has_27_vertices_on_a_neighbour_path() {
        let plan = GridPlan::new(&params()).unwrap();
        assert_eq!(plan.path.len(), 27);
        assert_eq!(plan.dims, [3, 3, 3]);
        assert!(plan.left_out.is_empty());
        for pair in plan.path.windows(2) {
            let step = (pair[1].position - pair[0].position).norm();
            assert!((step - 0.04).abs() < 1e-12, "serpentine step {step}");
        }
        let mut seen = plan.grid_index.clone();
        seen.sort();
        assert_eq!(seen, (0..27).collect::<Vec<_>>());
        assert!((plan.origin - Vector3::new(-0.04, -0.04, -0.04)).norm() < 1e-12);
    }

    #[test]
    fn vertices_outside_the_workspace_are_left_out() {
        let mut p = params();
        p.half_size = 2; // ±80 mm, workspace ±70 mm
        let plan = GridPlan::new(&p).unwrap();
        assert_eq!(plan.dims, [3, 3, 3]);
        assert_eq!(plan.left_out.len(), 125 - 27);
        assert!(plan
            .path
            .iter()
            .all(|v| v.position.iter().all(|c| c.abs() <= 0.07)));
        p.workspace = (
            Vector3::new(-0.07, -0.07, -0.01),
            Vector3::new(0.07, 0.07, 0.01),
        );
        p.half_size = 1;
        p.spacing = 0.05;
        let err = GridPlan::new(&p).unwrap_err();
        assert!(err.to_string().contains("along z"));
    }
}
