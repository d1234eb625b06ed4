//! `hgcd validate --sweep N`: how well a grid compensates everywhere the handle of a simulated
//! plant can go, not only at the experiment's 27 contact points. N points are drawn uniformly
//! from the plant's reachable workspace (inside its stops' bounding box, reachable within its
//! joint limits, outside any obstacle); at each, the compensation force F_G(X) is compared with
//! the plant's own holding force F_true(X) ([`crate::sim::Plant::holding_force`]): the residual
//! |F_true − F_G| / |F_true|. A point is *covered* when it lies in a cell of the grid whose
//! vertices were all measured: its force is interpolated between measurements. Elsewhere it is
//! extrapolated: in a cell with an extrapolated or unreachable vertex, or outside the grid's box
//! (`compensation.outside_grid`: the nearest face's values, or zero). The paper's cube and the
//! explored grid are swept over the same points. docs/calibration.md §11 reads the file.

use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;

use crate::config::Config;
use crate::control::compensation::GravityModel;
use crate::grid::GridFile;
use crate::sim::{SimDevice, SimError};

/// Draws per point at most: a workspace that fills less than 1/`MAX_DRAWS` of its bounding box
/// is refused rather than sampled for ever.
const MAX_DRAWS: usize = 1000;

/// A reachable point closer than this to where the plant put its handle counts as reached, m.
const PLACED: f64 = 1e-6;

/// A reachable point and the plant's holding force there (SI).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TruePoint {
    pub position: Vector3<f64>,
    pub holding_force: Vector3<f64>,
}

/// Percentiles of a residual over the sweep's points, %.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Percentiles {
    pub p50: f64,
    pub p95: f64,
    pub max: f64,
}

/// One grid over the sweep's points.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct GridSweep {
    /// Vertices of the grid, and how many of them were measured.
    pub vertices: usize,
    pub measured_vertices: usize,
    /// Share of the points in cells whose vertices were all measured, 0 to 1.
    pub covered_fraction: f64,
    /// |F_true − F_G| / |F_true| over all points, %.
    pub residual_pct: Percentiles,
    /// The same over the covered points only (None: no point covered).
    pub covered_residual_pct: Option<Percentiles>,
}

/// `sweep.json`: the points and each grid's figures, side by side.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Sweep {
    pub format: &'static str,
    pub device: String,
    pub points: usize,
    pub seed: u64,
    /// The grid of the paper: the cube the calibration measured (None: not calibrated).
    pub cube: Option<GridSweep>,
    /// The grid over the explored workspace (`calibration.workspace = "explore"`).
    pub explored: Option<GridSweep>,
}

/// A grid to sweep: its compensation and which of its vertices were measured.
#[derive(Clone, Debug)]
pub struct SweptGrid {
    pub model: GravityModel,
    /// Per vertex, grid order: measured (not unreachable, not extrapolated).
    pub measured: Vec<bool>,
}

impl SweptGrid {
    /// The grid of `file` under `model`: the vertices its `[calibration]` record lists as
    /// unreachable or extrapolated were not measured.
    pub fn new(model: GravityModel, file: &GridFile) -> Self {
        let grid = &model.grid;
        let mut measured = vec![true; grid.masses.len()];
        if let Some(c) = &file.calibration {
            let centre = Vector3::from(c.centre_mm.unwrap_or_default()) * 1e-3;
            let listed = c
                .unreachable_vertices
                .iter()
                .chain(&c.extrapolated_vertices);
            for k in listed.flatten() {
                let x = centre + Vector3::new(k[0] as f64, k[1] as f64, k[2] as f64) * grid.spacing;
                let at = (x - grid.origin) / grid.spacing;
                let i = at.map(|u| u.round());
                if (0..3).all(|a| i[a] >= 0.0 && (i[a] as usize) < grid.dims[a]) {
                    measured[grid.index(i[0] as usize, i[1] as usize, i[2] as usize)] = false;
                }
            }
        }
        Self { model, measured }
    }

    /// Whether the force at `x` is interpolated between measured vertices only.
    fn covers(&self, x: &Vector3<f64>) -> bool {
        let (idx, w) = self.model.grid.cell_weights(x);
        self.model.grid.contains(x) && (0..8).all(|n| w[n] == 0.0 || self.measured[idx[n]])
    }
}

/// Why the sweep could not run.
#[derive(Debug, thiserror::Error)]
pub enum SweepError {
    #[error("--sweep needs a simulated device: it compares with the plant's own holding force")]
    NotSimulated,
    #[error("--sweep {0} is out of range (1 to 1000000 points)")]
    Points(usize),
    #[error("the simulated device cannot be built for the sweep")]
    Simulation(#[source] SimError),
    #[error(
        "no reachable point in {MAX_DRAWS} draws from the workspace box of sim:{model}: \
         its reachable workspace is too thin to sample"
    )]
    Unreachable { model: String },
}

/// Points the sweep accepts.
pub const POINTS_RANGE: (usize, usize) = (1, 1_000_000);

/// The holding force at each of `n` points drawn from the reachable workspace of `sim:model`
/// (as `config` describes it, seed `seed`).
///
/// Errors: [`SweepError::Simulation`] for a config the simulator refuses,
/// [`SweepError::Unreachable`] for a workspace too thin to sample.
pub fn reachable_truth(
    model: &str,
    config: &Config,
    n: usize,
    seed: u64,
) -> Result<Vec<TruePoint>, SweepError> {
    let device = SimDevice::from_config(model, config).map_err(SweepError::Simulation)?;
    let (lo, hi) = device.plant().workspace();
    let obstacle = config.sim.obstacle();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut placed = config.clone();
    let mut points = Vec::with_capacity(n);
    while points.len() < n {
        let mut found = None;
        for _ in 0..MAX_DRAWS {
            let x = Vector3::from_fn(|a, _| rng.gen_range(lo[a]..=hi[a]));
            if obstacle.is_some_and(|(o_lo, o_hi)| (0..3).all(|a| x[a] > o_lo[a] && x[a] < o_hi[a]))
            {
                continue;
            }
            placed.sim.start_position_mm = (x * 1e3).into();
            let Ok(at) = SimDevice::from_config(model, &placed) else {
                continue;
            };
            let plant = at.plant();
            if (plant.position() - x).norm() <= PLACED {
                found = Some(TruePoint {
                    position: x,
                    holding_force: plant.holding_force(),
                });
                break;
            }
        }
        points.push(found.ok_or_else(|| SweepError::Unreachable {
            model: model.to_string(),
        })?);
    }
    Ok(points)
}

impl GridSweep {
    /// `grid` over `truth` ([`reachable_truth`]).
    pub fn new(grid: &SweptGrid, truth: &[TruePoint]) -> Self {
        let mut all = Vec::with_capacity(truth.len());
        let mut covered = Vec::new();
        for TruePoint {
            position: x,
            holding_force: f_true,
        } in truth
        {
            let residual = 100.0 * (f_true - grid.model.force(x)).norm() / f_true.norm();
            all.push(residual);
            if grid.covers(x) {
                covered.push(residual);
            }
        }
        Self {
            vertices: grid.measured.len(),
            measured_vertices: grid.measured.iter().filter(|&&m| m).count(),
            covered_fraction: covered.len() as f64 / truth.len().max(1) as f64,
            residual_pct: Percentiles::of(&mut all),
            covered_residual_pct: (!covered.is_empty()).then(|| Percentiles::of(&mut covered)),
        }
    }
}

impl Percentiles {
    /// Nearest-rank percentiles of `values` (sorted here; NaN, from a zero true force, last).
    fn of(values: &mut [f64]) -> Self {
        values.sort_by(f64::total_cmp);
        let rank = |p: f64| {
            let k = ((p * values.len() as f64).ceil() as usize).clamp(1, values.len());
            values[k - 1]
        };
        Self {
            p50: rank(0.50),
            p95: rank(0.95),
            max: rank(1.0),
        }
    }
}

impl Sweep {
    /// The sweep of the paper's `cube` and the `explored` grid over the same `n` points of
    /// `sim:model` (seed `seed`).
    ///
    /// Errors: as [`reachable_truth`].
    pub fn run(
        model: &str,
        config: &Config,
        cube: Option<&SweptGrid>,
        explored: Option<&SweptGrid>,
        n: usize,
        seed: u64,
    ) -> Result<Self, SweepError> {
        if n < POINTS_RANGE.0 || n > POINTS_RANGE.1 {
            return Err(SweepError::Points(n));
        }
        let truth = reachable_truth(model, config, n, seed)?;
        Ok(Self {
            format: "hgcd-sweep/1",
            device: format!("sim:{model}"),
            points: n,
            seed,
            cube: cube.map(|g| GridSweep::new(g, &truth)),
            explored: explored.map(|g| GridSweep::new(g, &truth)),
        })
    }

    /// The file's text.
    pub fn json(&self) -> String {
        serde_json::to_string_pretty(self).expect("plain numbers and strings") + "\n"
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percentiles_are_nearest_rank() {
        let mut v: Vec<f64> = (1..=100).rev().map(f64::from).collect();
        let p = Percentiles::of(&mut v);
        assert_eq!((p.p50, p.p95, p.max), (50.0, 95.0, 100.0));
        let p = Percentiles::of(&mut [3.0]);
        assert_eq!((p.p50, p.p95, p.max), (3.0, 3.0, 3.0));
    }

    #[test]
    fn points_on_a_point_mass_avoid_its_obstacle_and_stay_in_its_box() {
        let mut config = Config::default();
        config.sim.obstacle_min_mm = Some([-80.0, -80.0, -80.0]);
        config.sim.obstacle_max_mm = Some([80.0, 80.0, 0.0]);
        let truth = reachable_truth("point-mass", &config, 200, 3).unwrap();
        assert_eq!(truth.len(), 200);
        for TruePoint {
            position: x,
            holding_force: f,
        } in &truth
        {
            assert!(x.z >= 0.0, "{x:?} inside the obstacle");
            assert!(x.amax() <= 0.08 + 1e-12, "{x:?} outside the box");
            // The default point mass: 120 g, uniform, gravity along z.
            assert!(
                (f.norm() - 0.12 * 9.81).abs() < 1e-9 && f.z.abs() == f.norm(),
                "{f:?}"
            );
        }
    }

    #[test]
    fn points_on_a_linkage_are_within_its_joint_limits() {
        let config = Config::default();
        let truth = reachable_truth("phantom", &config, 100, 1).unwrap();
        for TruePoint { position: x, .. } in &truth {
            let mut at = config.clone();
            at.sim.start_position_mm = (x * 1e3).into();
            let device = SimDevice::from_config("phantom", &at).expect("reachable");
            assert!((device.plant().position() - x).norm() < 1e-6);
        }
        // Not a box: some of the box's corners are out of the arm's reach.
        let (lo, hi) = SimDevice::from_config("phantom", &config)
            .unwrap()
            .plant()
            .workspace();
        let mut corner = config.clone();
        corner.sim.start_position_mm = (Vector3::new(hi.x, hi.y, lo.z) * 1e3).into();
        assert!(SimDevice::from_config("phantom", &corner).is_err());
    }
}
