//! `hgcd validate --sweep N`: how well a grid compensates everywhere the handle of a simulated
//! plant can go, not only at the experiment's 27 contact points. N points are drawn uniformly
//! from the plant's reachable workspace (inside its stops' bounding box, reachable within its
//! joint limits, outside any obstacle); at each, the compensation force F_G(X) is compared with
//! the plant's own holding force F_true(X) ([`crate::sim::Plant::holding_force`]): the residual
//! |F_true − F_G| / |F_true|. A point is *covered* when it lies in a cell of the grid whose
//! vertices were all measured: its force is interpolated between measurements. Elsewhere it is
//! extrapolated: in a cell with an extrapolated or unreachable vertex, or outside the grid's box
//! (`compensation.outside_grid`: the nearest face's values, or zero). The paper's cube and the
//! explored grid are swept over the same points, beside the [`ExactLattice`]: what a lattice of
//! the calibration's spacing allows at best, holding the plant's own force at every vertex the
//! handle can reach. docs/calibration.md §11 reads the file.

use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;

use crate::config::{CompensationMode, Config, OutsideGrid};
use crate::control::compensation::GravityModel;
use crate::grid::{extrapolate_from_neighbours, GridFile, MassGrid};
use crate::sim::{SimDevice, SimError};

/// Draws per point at most: a workspace that fills less than 1/`MAX_DRAWS` of its bounding box
/// is refused rather than sampled for ever.
const MAX_DRAWS: usize = 1000;

/// The exact lattice is left out of a sweep when it would hold more vertices than this (a
/// spacing of a few millimetres over a large workspace): each vertex places the plant once.
pub const MAX_LATTICE_VERTICES: usize = 200_000;

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
    /// The gravity model swept: the compensation mode the grid is used in ("scalar",
    /// "vector", "arm", "arm-residual").
    pub model: String,
    /// Vertices of the grid, and how many of them were measured.
    pub vertices: usize,
    pub measured_vertices: usize,
    /// Share of the points in cells whose vertices were all measured, 0 to 1.
    pub covered_fraction: f64,
    /// |F_true − F_G| / |F_true| over all points, %.
    pub residual_pct: Percentiles,
    /// |F_true − F_G| over all points, mN.
    pub residual_mn: Percentiles,
    /// The same over the covered points only (None: no point covered).
    pub covered_residual_pct: Option<Percentiles>,
}

/// The best a lattice of the calibration's spacing can do on the plant: its vertices aligned on
/// X_C (`calibration.centre_mm`) over the plant's whole workspace box, each reachable vertex
/// holding the plant's own force there (no calibration error, no margin from the stops), the
/// others extrapolated from them as an explored grid's are (docs/grid-format.md §4), and
/// interpolated trilinearly in vector mode. Whatever a calibration measures, a grid of that
/// spacing does not do better than this over the whole workspace.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ExactLattice {
    pub spacing_mm: f64,
    /// The lattice over the points: `measured_vertices` are the reachable ones.
    #[serde(flatten)]
    pub sweep: GridSweep,
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
    /// The bound the spacing sets (None: more than [`MAX_LATTICE_VERTICES`] vertices).
    pub exact_lattice: Option<ExactLattice>,
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
        let measured = file.measured();
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
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut placed = config.clone();
    let mut points = Vec::with_capacity(n);
    while points.len() < n {
        let found = (0..MAX_DRAWS).find_map(|_| {
            let x = Vector3::from_fn(|a, _| rng.gen_range(lo[a]..=hi[a]));
            true_point(model, &mut placed, &x)
        });
        points.push(found.ok_or_else(|| SweepError::Unreachable {
            model: model.to_string(),
        })?);
    }
    Ok(points)
}

/// The plant's holding force at `x` if the handle can be there: outside the obstacle and
/// within the joint limits (`placed` is the config, its start position moved to `x`).
fn true_point(model: &str, placed: &mut Config, x: &Vector3<f64>) -> Option<TruePoint> {
    if let Some((lo, hi)) = placed.sim.obstacle() {
        if (0..3).all(|a| x[a] > lo[a] && x[a] < hi[a]) {
            return None;
        }
    }
    placed.sim.start_position_mm = (x * 1e3).into();
    let at = SimDevice::from_config(model, placed).ok()?;
    let plant = at.plant();
    ((plant.position() - x).norm() <= PLACED).then(|| TruePoint {
        position: *x,
        holding_force: plant.holding_force(),
    })
}

impl ExactLattice {
    /// The lattice of `config`'s spacing and centre over the workspace box of `sim:model`,
    /// swept over `truth`; None if it has more than [`MAX_LATTICE_VERTICES`] vertices.
    ///
    /// Errors: [`SweepError::Simulation`] for a config the simulator refuses.
    pub fn new(
        model: &str,
        config: &Config,
        truth: &[TruePoint],
    ) -> Result<Option<Self>, SweepError> {
        let device = SimDevice::from_config(model, config).map_err(SweepError::Simulation)?;
        let (lo, hi) = device.plant().workspace();
        let spacing = config.calibration.spacing_mm * 1e-3;
        let centre = Vector3::from(config.calibration.centre_mm) * 1e-3;
        let first = ((lo - centre) / spacing).map(f64::floor);
        let last = ((hi - centre) / spacing).map(f64::ceil);
        let dims = [0, 1, 2].map(|a| (last[a] - first[a]).max(0.0) as usize + 1);
        let count = dims.iter().try_fold(1usize, |n, &d| n.checked_mul(d));
        if count.is_none_or(|n| n > MAX_LATTICE_VERTICES) {
            return Ok(None);
        }
        let up = Vector3::from(config.sim.gravity_direction).normalize();
        let grid = MassGrid::uniform(
            0.0,
            config.sim.g,
            up,
            centre + first * spacing,
            spacing,
            dims,
        );
        let mut forces = vec![Vector3::zeros(); grid.vertex_count()];
        let mut reachable = vec![false; grid.vertex_count()];
        let mut placed = config.clone();
        for k in 0..dims[2] {
            for j in 0..dims[1] {
                for i in 0..dims[0] {
                    let x = grid.vertex_position(i, j, k);
                    if let Some(point) = true_point(model, &mut placed, &x) {
                        let n = grid.index(i, j, k);
                        forces[n] = point.holding_force;
                        reachable[n] = true;
                    }
                }
            }
        }
        if !reachable.contains(&true) {
            return Ok(None);
        }
        extrapolate_from_neighbours(dims, &mut forces, &reachable);
        let mut file = GridFile::from(grid);
        file.vertices.force_vectors = forces.iter().map(|&f| f.into()).collect();
        let model = GravityModel::new(file, CompensationMode::Vector, OutsideGrid::HoldNearest)
            .expect("a force vector for every vertex");
        let lattice = SweptGrid {
            model,
            measured: reachable,
        };
        Ok(Some(Self {
            spacing_mm: config.calibration.spacing_mm,
            sweep: GridSweep::new(&lattice, truth),
        }))
    }
}

impl GridSweep {
    /// `grid` over `truth` ([`reachable_truth`]).
    pub fn new(grid: &SweptGrid, truth: &[TruePoint]) -> Self {
        let mut all = Vec::with_capacity(truth.len());
        let mut absolute = Vec::with_capacity(truth.len());
        let mut covered = Vec::new();
        for TruePoint {
            position: x,
            holding_force: f_true,
        } in truth
        {
            let error = (f_true - grid.model.force(x)).norm();
            let residual = 100.0 * error / f_true.norm();
            all.push(residual);
            absolute.push(error * 1e3);
            if grid.covers(x) {
                covered.push(residual);
            }
        }
        Self {
            model: grid.model.mode.to_string(),
            vertices: grid.measured.len(),
            measured_vertices: grid.measured.iter().filter(|&&m| m).count(),
            covered_fraction: covered.len() as f64 / truth.len().max(1) as f64,
            residual_pct: Percentiles::of(&mut all),
            residual_mn: Percentiles::of(&mut absolute),
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
            exact_lattice: ExactLattice::new(model, config, &truth)?,
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

    #[test]
    fn the_exact_lattice_of_a_point_mass_is_exact_and_skips_the_obstacle() {
        let mut config = Config::default();
        config.calibration.spacing_mm = 20.0;
        config.sim.obstacle_min_mm = Some([-80.0, -80.0, -80.0]);
        config.sim.obstacle_max_mm = Some([80.0, 80.0, 0.0]);
        let truth = reachable_truth("point-mass", &config, 300, 2).unwrap();
        let lattice = ExactLattice::new("point-mass", &config, &truth)
            .unwrap()
            .expect("a small lattice");
        // −80 … 80 mm along each axis, the plant's stops; the obstacle holds the vertices strictly
        // inside it, −60 … 60 mm along x and y (7 a side) and −60 … −20 mm along z (3).
        assert_eq!(lattice.sweep.vertices, 9 * 9 * 9);
        assert_eq!(lattice.sweep.measured_vertices, 9 * 9 * 9 - 7 * 7 * 3);
        // A uniform field is carried on exactly, into the obstacle and past the box.
        assert!(lattice.sweep.residual_pct.max < 1e-9, "{lattice:?}");
        assert_eq!(lattice.spacing_mm, 20.0);
    }

    /// The bound a lattice sets on the linkages, against their own holding force: on the
    /// PHANToM no lattice of 40 mm (the default spacing) or even 20 mm holds the force within
    /// 5 % at 95 % of the reachable points, though it holds the plant's exact force at every
    /// vertex the handle can reach; halving the spacing shrinks the residual (the field is
    /// smooth), but its curvature near the workspace's edge, where the lattice can only
    /// extrapolate, is what is left (docs/calibration.md §12).
    #[test]
    fn a_lattice_bounds_the_residual_on_a_linkage_whatever_the_calibration() {
        for model in ["phantom", "delta"] {
            let mut p95 = Vec::new();
            for spacing_mm in [40.0, 30.0, 20.0] {
                let mut config = Config::default();
                config.calibration.spacing_mm = spacing_mm;
                let truth = reachable_truth(model, &config, 1000, 1).unwrap();
                let lattice = ExactLattice::new(model, &config, &truth).unwrap().unwrap();
                let s = &lattice.sweep;
                let r = &s.residual_pct;
                println!(
                    "{model} at {spacing_mm} mm: {} of {} vertices reachable, covers {:.1} %, \
                     residual p50 {:.1} %, p95 {:.1} %, max {:.1} %",
                    s.measured_vertices,
                    s.vertices,
                    100.0 * s.covered_fraction,
                    r.p50,
                    r.p95,
                    r.max
                );
                p95.push(r.p95);
            }
            assert!(p95[0] > 10.0, "{model}: {p95:?}");
            assert!(p95[2] < 0.6 * p95[0], "{model}: {p95:?}");
            if model == "phantom" {
                assert!(p95[2] > 5.0, "{model}: {p95:?}");
            }
        }
    }
}
