//! The grid to calibrate: the vertices (nL, mL, pL) + centre with n, m, p ∈ [−N, N], the ones
//! left out, and the order they are visited in.
//!
//! A vertex outside the workspace box is left out together with every vertex on its index plane,
//! so the vertices kept form a rectangular sub-grid (at least 2 along each axis). They are visited
//! along a serpentine path, so the previous vertex is always a neighbour (Eq. 12 starts each
//! vertex from the mass of the closest previous one).

use nalgebra::Vector3;

use super::explore::{WorkspaceMap, MARGIN};
use super::{CalibrationFailure, CalibrationParams, Holds};

/// Most vertices along one axis of an explored grid: room for the largest explored grid is made
/// before the run (replanning happens on the servo thread, which must not allocate).
pub const MAX_EXPLORED_SIDE: usize = 20;
const MAX_EXPLORED: usize = MAX_EXPLORED_SIDE * MAX_EXPLORED_SIDE * MAX_EXPLORED_SIDE;
/// Share of a cell the explored reach may pass a lattice plane by without another layer.
const LAYER_SLACK: f64 = 0.05;

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
    /// Vertices of an explored grid outside the explored workspace (less its margin), with
    /// their flat indices: not visited, their values extrapolated from the calibrated ones.
    pub extrapolated: Vec<(Vertex, usize)>,
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
        let mut plan = Self {
            origin: at([kept[0][0], kept[1][0], kept[2][0]]),
            path,
            grid_index,
            dims,
            left_out,
            extrapolated: Vec::new(),
        };
        if params.workspace_mode == crate::config::WorkspaceMode::Cube {
            let dims = plan.dims;
            match params.holds {
                Holds::Every => {}
                // The corners are the vertices farthest apart in joint angles, where the arm
                // model's parameters are best conditioned.
                Holds::Corners => plan.keep(|c| (0..3).all(|a| c[a] == 0 || c[a] == dims[a] - 1)),
                Holds::Diagonal => {
                    plan.keep(|c| c == [0, 0, 0] || (0..3).all(|a| c[a] == dims[a] - 1))
                }
            }
        }
        Ok(plan)
    }

    /// Visit only the vertices whose grid coordinates `held` accepts, in the serpentine's
    /// order; the others are not visited, their values filled from these.
    fn keep(&mut self, held: impl Fn([usize; 3]) -> bool) {
        let dims = self.dims;
        let coordinates = |n: usize| {
            [
                n % dims[0],
                (n / dims[0]) % dims[1],
                n / (dims[0] * dims[1]),
            ]
        };
        let mut path = Vec::with_capacity(self.path.len());
        let mut grid_index = Vec::with_capacity(self.path.len());
        for (vertex, &n) in self.path.iter().zip(&self.grid_index) {
            if held(coordinates(n)) {
                path.push(*vertex);
                grid_index.push(n);
            } else {
                self.extrapolated.push((*vertex, n));
            }
        }
        self.path = path;
        self.grid_index = grid_index;
    }

    /// Make room for an explored grid ([`GridPlan::explore`]) of up to
    /// `MAX_EXPLORED_SIDE`³ vertices.
    pub fn reserve_explored(&mut self) {
        self.path.reserve(MAX_EXPLORED);
        self.grid_index.reserve(MAX_EXPLORED);
        self.extrapolated.reserve(MAX_EXPLORED);
    }

    /// Replan on the lattice X_C + L (n, m, p) over the box of what `map` reached: the vertices
    /// at least [`MARGIN`] inside the explored workspace are visited in serpentine order, the
    /// others extrapolated. Allocates nothing after [`GridPlan::reserve_explored`].
    ///
    /// Errors: [`CalibrationFailure::ExploredTooLarge`] for more than `MAX_EXPLORED_SIDE`
    /// vertices along an axis, [`CalibrationFailure::NothingExplored`] for none to visit.
    pub fn explore(&mut self, map: &WorkspaceMap, spacing: f64) -> Result<(), CalibrationFailure> {
        let centre = map.centre;
        let (lo, hi) = map.extent();
        let mut first = [0i32; 3];
        let mut dims = [0usize; 3];
        for a in 0..3 {
            // A reach that ends within a twentieth of a cell beyond a lattice plane (X_C rests a
            // few µm off the configured centre) adds no layer: the grid's faces hold it.
            let k_lo = ((lo[a] - centre[a]) / spacing + LAYER_SLACK).floor() as i32;
            let k_hi = ((hi[a] - centre[a]) / spacing - LAYER_SLACK).ceil() as i32;
            let needed = (k_hi - k_lo + 1).max(2) as usize;
            if needed > MAX_EXPLORED_SIDE {
                return Err(CalibrationFailure::ExploredTooLarge {
                    axis: ['x', 'y', 'z'][a],
                    needed,
                });
            }
            first[a] = k_lo;
            dims[a] = needed;
        }
        let at = |k: [i32; 3]| {
            centre + Vector3::new(f64::from(k[0]), f64::from(k[1]), f64::from(k[2])) * spacing
        };
        self.path.clear();
        self.grid_index.clear();
        self.extrapolated.clear();
        self.left_out.clear();
        let mut row = 0usize;
        for kz in 0..dims[2] {
            for jy_step in 0..dims[1] {
                let jy = if kz % 2 == 0 {
                    jy_step
                } else {
                    dims[1] - 1 - jy_step
                };
                for ix_step in 0..dims[0] {
                    let ix = if row % 2 == 0 {
                        ix_step
                    } else {
                        dims[0] - 1 - ix_step
                    };
                    let index = [
                        first[0] + ix as i32,
                        first[1] + jy as i32,
                        first[2] + kz as i32,
                    ];
                    let vertex = Vertex {
                        index,
                        position: at(index),
                    };
                    let flat = ix + dims[0] * (jy + dims[1] * kz);
                    if map.contains(&vertex.position, MARGIN) {
                        self.path.push(vertex);
                        self.grid_index.push(flat);
                    } else {
                        self.extrapolated.push((vertex, flat));
                    }
                }
                row += 1;
            }
        }
        if self.path.is_empty() {
            return Err(CalibrationFailure::NothingExplored {
                margin_mm: MARGIN * 1e3,
            });
        }
        self.origin = at(first);
        self.dims = dims;
        Ok(())
    }

    /// The most vertices the grid can end with, left-out ones included: the cube's, or the
    /// largest explored grid's once room is made for one.
    pub fn most_vertices(&self) -> usize {
        let planned = self.path.len() + self.left_out.len() + self.extrapolated.len();
        if self.extrapolated.capacity() >= MAX_EXPLORED {
            planned.max(MAX_EXPLORED)
        } else {
            planned
        }
    }

    /// Vertices in the grid: visited and extrapolated.
    pub fn vertex_count(&self) -> usize {
        self.dims.iter().product()
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
