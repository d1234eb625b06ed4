//! Off-line autocalibration (paper §3, Algorithm 1) as a tick-driven state machine.
//!
//! 1. **Initialisation** (§3.1): an elastic field k_init (X_C − X) (plus a little damping, beyond
//!    the paper, so a frictionless handle settles) holds the handle near where it rests. At steady
//!    state the sag gives the gravity direction v_G (Eq. 7) and a rough mass M̂_0 (Eq. 8).
//! 2. **Vertices** (§3.2): a feedback-linearised PD (k_D = αM, k_P = βM) moves to each grid
//!    vertex along a minimum-jerk path and holds it with the gravity term M_j g v_G (Eq. 10). At
//!    each steady state the mass is updated with the *signed* form of Eq. 11,
//!    M_{j+1} = M_j + k_P (X_i − X̄)·v_G / g (the paper's norm loses the sign; see docs), and the
//!    whole holding force k_P (X_i − X̄) + M_j g v_G is kept for the vector mode. The next vertex
//!    starts from this one's mass (Eqs. 12, 14). Unlike Eq. 13 (k_P(i,j) = β M_{j−1}), the gains
//!    follow the newest estimate: lagged gains leave the loop mis-linearised for a whole iteration
//!    after a large correction. If a hold finds no steady state for a second, its gains are
//!    halved (at most three times): gains built on a mass several times too large oscillate
//!    through the velocity filter's lag.
//!
//! Steady state ("n consecutive samples within a sphere of radius ε") means: n consecutive
//! samples, taken after the settle time since the last change, all within ε of the first of them,
//! whose mean X̄ agrees within ε/10 with the mean of the n samples before them (no creep, no
//! drift; small oscillations average out).
//! A vertex ends at the second consecutive steady state within ε_M of the vertex along v_G (the
//! only direction a mass update moves it): its last update is then measured at the vertex, after
//! a transient too small to bias it.
//! Vertices are visited along a serpentine path, so the previous vertex is always a neighbour.

use crossbeam_channel::Sender;
use nalgebra::Vector3;

use super::pd::{LinearisedGains, PointHold};
use super::{ControlOutput, Controller, DeviceState};
use crate::config::Config;

/// Calibration parameters in SI units.
#[derive(Clone, Debug, PartialEq)]
pub struct CalibrationParams {
    /// Cube side L, m.
    pub spacing: f64,
    /// N: vertex indices run over [−N, N] on each axis.
    pub half_size: u32,
    /// Grid centre, m.
    pub centre: Vector3<f64>,
    /// Initial field stiffness, N/m.
    pub k_init: f64,
    /// Initial field damping, N·s/m.
    pub init_damping: f64,
    pub n_init: usize,
    /// m.
    pub eps_init: f64,
    pub n_m: usize,
    /// m.
    pub eps_m: f64,
    /// m/s².
    pub g: f64,
    pub gains: LinearisedGains,
    /// Time after a move or a mass update before steady-state samples count, s (2 × rise time).
    pub settle_time: f64,
    /// Duration of a one-cell move, s; longer moves take proportionally longer.
    pub move_time: f64,
    /// Limit per vertex (and for the initialisation), s.
    pub vertex_timeout: f64,
    pub max_iterations: u32,
    /// Box the handle may be driven in, m.
    pub workspace: (Vector3<f64>, Vector3<f64>),
}

impl CalibrationParams {
    pub fn from_config(config: &Config) -> Self {
        let c = &config.calibration;
        let rise_time = c.rise_time();
        Self {
            spacing: c.spacing(),
            half_size: c.half_size,
            centre: c.centre(),
            k_init: c.k_init(),
            init_damping: c.init_damping_n_s_per_m,
            n_init: c.n_init,
            eps_init: c.eps_init(),
            n_m: c.n_m,
            eps_m: c.eps_m(),
            g: c.g,
            gains: LinearisedGains::from_rise_time(rise_time, c.damping_ratio),
            settle_time: 2.0 * rise_time,
            move_time: c.move_time(),
            vertex_timeout: c.vertex_timeout_s,
            max_iterations: c.max_iterations,
            workspace: config.device.workspace(),
        }
    }
}

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
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
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

/// What was measured at one vertex.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VertexResult {
    pub vertex: Vertex,
    /// Apparent mass M̂(X_i), kg.
    pub mass: f64,
    /// Whole holding force at the last steady state, N (vector form of Eq. 11).
    pub force: Vector3<f64>,
    /// Mass updates made.
    pub iterations: u32,
    /// Distance from the vertex at the last steady state, m.
    pub final_error: f64,
    /// Device time spent on this vertex, move included, s.
    pub duration: f64,
}

/// A finished calibration.
#[derive(Clone, Debug, PartialEq)]
pub struct CalibrationResult {
    /// Unit v_G (Eq. 7).
    pub gravity_direction: Vector3<f64>,
    /// M̂_0 (Eq. 8), kg.
    pub initial_mass: f64,
    /// Rest point X_C and steady state X(∞) of the initialisation, m.
    pub rest_point: Vector3<f64>,
    pub initial_steady_state: Vector3<f64>,
    /// Results in grid order (x fastest).
    pub vertices: Vec<VertexResult>,
    pub origin: Vector3<f64>,
    pub dims: [usize; 3],
    pub left_out: Vec<Vertex>,
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
        "initialisation: the handle came to rest but sagged only {sag_mm:.3} mm under the field; \
         either something holds it, or it weighs less than {min_mass_g:.0} g (then lower \
         calibration.k_init_n_per_mm)"
    )]
    NoSag { sag_mm: f64, min_mass_g: f64 },
    #[error(
        "{vertex} did not converge within {timeout:.0} s ({iterations} mass updates); the handle \
         may be blocked by a stop, the vertex may lie outside the reachable workspace, or \
         calibration.eps_m_mm may be below the position noise"
    )]
    VertexTimeout {
        vertex: Vertex,
        timeout: f64,
        iterations: u32,
    },
    #[error(
        "{vertex} could not be reached: the handle settled {distance_mm:.1} mm away from it (a \
         mechanical stop or an obstacle? check device.workspace_*_mm)"
    )]
    Unreachable { vertex: Vertex, distance_mm: f64 },
    #[error("{vertex} did not converge after {iterations} mass updates")]
    TooManyIterations { vertex: Vertex, iterations: u32 },
    #[error(
        "{vertex}: the apparent mass came out as {mass:.4} kg; hgcd-grid/1 needs positive masses \
         (is the device over-balanced here?)"
    )]
    NonPositiveMass { vertex: Vertex, mass: f64 },
}

/// Progress, sent with `try_send` from the servo thread.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum CalibrationEvent {
    InitStarted,
    InitDone {
        gravity_direction: Vector3<f64>,
        initial_mass: f64,
    },
    VertexStarted {
        vertex: usize,
        of: usize,
        at: Vertex,
    },
    Iteration {
        vertex: usize,
        iteration: u32,
        mass: f64,
        error: f64,
    },
    /// No steady state came at a hold: the gains were scaled by `scale`.
    GainsReduced {
        vertex: usize,
        scale: f64,
    },
    VertexDone {
        vertex: usize,
        of: usize,
        mass: f64,
        iterations: u32,
    },
    Finished,
    Failed(CalibrationFailure),
}

/// n consecutive samples within ε of the first of them, whose mean agrees within ε/10 with the
/// mean of the n samples before them (the handle is neither creeping toward its equilibrium nor
/// drifting; an oscillation much smaller than ε averages out); yields their mean.
#[derive(Clone, Debug)]
struct SteadyState {
    n: usize,
    eps: f64,
    first: Vector3<f64>,
    sum: Vector3<f64>,
    count: usize,
    previous_mean: Option<Vector3<f64>>,
}

impl SteadyState {
    fn new(n: usize, eps: f64) -> Self {
        Self {
            n,
            eps,
            first: Vector3::zeros(),
            sum: Vector3::zeros(),
            count: 0,
            previous_mean: None,
        }
    }
    fn reset(&mut self) {
        self.count = 0;
        self.previous_mean = None;
    }
    fn push(&mut self, x: &Vector3<f64>) -> Option<Vector3<f64>> {
        if self.count == 0 {
            self.first = *x;
            self.sum = Vector3::zeros();
        } else if (x - self.first).norm() > self.eps {
            self.first = *x;
            self.sum = Vector3::zeros();
            self.count = 0;
            self.previous_mean = None;
        }
        self.sum += x;
        self.count += 1;
        if self.count < self.n {
            return None;
        }
        let mean = self.sum / self.n as f64;
        self.count = 0;
        match self.previous_mean.replace(mean) {
            Some(previous) if (mean - previous).norm() < self.eps / 10.0 => Some(mean),
            _ => None,
        }
    }
}

/// The initial steady state must sag more than this many ε_init below X_C (else something still
/// holds the handle): 0.3 mm, the sag of 15 g, with the paper's defaults.
const MIN_SAG: f64 = 3.0;

/// How long a hold may go without a steady state (after the settle time) before the gains are
/// halved, s.
const GAIN_BACKOFF_AFTER: f64 = 1.0;

fn minimum_jerk(tau: f64) -> f64 {
    let t = tau.clamp(0.0, 1.0);
    t * t * t * (10.0 - 15.0 * t + 6.0 * t * t)
}

#[derive(Clone, Copy, Debug)]
enum Phase {
    Start,
    Init {
        /// Where the handle was when calibration started.
        from: Vector3<f64>,
        /// Centre X_C of the initial field once the glide is over.
        rest_point: Vector3<f64>,
        since: f64,
        /// Duration of the field centre's glide from `from` to `rest_point`, s (0: none).
        glide: f64,
    },
    Move {
        from: Vector3<f64>,
        start: f64,
        duration: f64,
    },
    Hold {
        since_change: f64,
    },
    Finished,
    Failed(CalibrationFailure),
}

/// The calibration controller. Build it, run it in the servo loop until it is done, then take
/// [`Calibration::outcome`].
#[derive(Debug)]
pub struct Calibration {
    params: CalibrationParams,
    plan: GridPlan,
    events: Option<Sender<CalibrationEvent>>,
    phase: Phase,
    detector: SteadyState,
    gravity_direction: Vector3<f64>,
    initial_mass: f64,
    rest_point: Vector3<f64>,
    initial_steady_state: Vector3<f64>,
    start_time: f64,
    /// Current vertex (index into the plan's path).
    vertex: usize,
    vertex_start: f64,
    /// M_j(X_i): the mass in the gravity term.
    mass: f64,
    /// The mass the PD gains are built on: the newest estimate (M̂(X_{i−1}) while moving, Eq. 14).
    gain_mass: f64,
    /// Back-off factor on the gains (1, ½, ¼, ⅛) when a hold finds no steady state.
    gain_scale: f64,
    iteration: u32,
    /// Sag at the last initial steady state, m.
    init_sag: Option<f64>,
    /// Whether the previous steady state at this vertex was within ε_M of it.
    previous_near: bool,
    /// Distance from the vertex at the previous steady state, m.
    previous_error: f64,
    results: Vec<Option<VertexResult>>,
    end_time: f64,
}

impl Calibration {
    pub fn new(
        params: CalibrationParams,
        events: Option<Sender<CalibrationEvent>>,
    ) -> Result<Self, PlanError> {
        let plan = GridPlan::new(&params)?;
        let count = plan.path.len();
        Ok(Self {
            detector: SteadyState::new(params.n_init, params.eps_init),
            params,
            plan,
            events,
            phase: Phase::Start,
            gravity_direction: Vector3::z(),
            initial_mass: 0.0,
            rest_point: Vector3::zeros(),
            initial_steady_state: Vector3::zeros(),
            start_time: 0.0,
            vertex: 0,
            vertex_start: 0.0,
            mass: 0.0,
            gain_mass: 0.0,
            gain_scale: 1.0,
            iteration: 0,
            init_sag: None,
            previous_near: false,
            previous_error: f64::INFINITY,
            results: vec![None; count],
            end_time: 0.0,
        })
    }

    /// The planned grid (vertices, left-out vertices).
    pub fn plan(&self) -> &GridPlan {
        &self.plan
    }

    fn emit(&self, event: CalibrationEvent) {
        if let Some(tx) = &self.events {
            let _ = tx.try_send(event);
        }
    }

    /// After a successful run: the hold at the last vertex (its PD and its measured gravity
    /// term), to keep the handle up until the new grid is in use.
    pub fn final_hold(&self) -> Option<PointHold> {
        if !matches!(self.phase, Phase::Finished) {
            return None;
        }
        let last = self.results.last().copied().flatten()?;
        Some(PointHold {
            set_point: last.vertex.position,
            mass: last.mass,
            gravity_direction: self.gravity_direction,
            g: self.params.g,
            gains: self.params.gains,
        })
    }

    /// The result once finished, the failure if it failed, None while running (or if aborted).
    pub fn outcome(&self) -> Option<Result<CalibrationResult, CalibrationFailure>> {
        match self.phase {
            Phase::Failed(f) => Some(Err(f)),
            Phase::Finished => {
                let mut vertices: Vec<VertexResult> = Vec::with_capacity(self.results.len());
                let mut ordered = vec![None; self.results.len()];
                for (k, r) in self.results.iter().enumerate() {
                    ordered[self.plan.grid_index[k]] = *r;
                }
                for r in ordered {
                    vertices.push(r?);
                }
                Some(Ok(CalibrationResult {
                    gravity_direction: self.gravity_direction,
                    initial_mass: self.initial_mass,
                    rest_point: self.rest_point,
                    initial_steady_state: self.initial_steady_state,
                    vertices,
                    origin: self.plan.origin,
                    dims: self.plan.dims,
                    left_out: self.plan.left_out.clone(),
                    duration: self.end_time - self.start_time,
                }))
            }
            _ => None,
        }
    }

    fn fail(&mut self, failure: CalibrationFailure) -> ControlOutput {
        self.phase = Phase::Failed(failure);
        self.emit(CalibrationEvent::Failed(failure));
        ControlOutput::done(Vector3::zeros())
    }

    fn start_move(&mut self, from: Vector3<f64>, t: f64) {
        let to = self.plan.path[self.vertex].position;
        let cells = (to - from).norm() / self.params.spacing;
        self.phase = Phase::Move {
            from,
            start: t,
            duration: self.params.move_time * cells.max(1.0),
        };
        self.vertex_start = t;
        self.iteration = 0;
        self.previous_near = false;
        self.previous_error = f64::INFINITY;
        self.detector = SteadyState::new(self.params.n_m, self.params.eps_m);
        self.emit(CalibrationEvent::VertexStarted {
            vertex: self.vertex,
            of: self.plan.path.len(),
            at: self.plan.path[self.vertex],
        });
    }

    /// Feedback-linearised PD toward `target` plus the gravity term M_j g v_G (Eq. 10).
    fn pd_force(&self, target: &Vector3<f64>, s: &DeviceState) -> Vector3<f64> {
        let gains = &self.params.gains;
        let m = self.gain_mass * self.gain_scale;
        (target - s.position) * gains.stiffness(m) - s.velocity * gains.damping(m)
            + self.gravity_direction * (self.mass * self.params.g)
    }
}

impl Controller for Calibration {
    fn tick(&mut self, s: &DeviceState) -> ControlOutput {
        let t = s.time;
        match self.phase {
            Phase::Finished | Phase::Failed(_) => ControlOutput::done(Vector3::zeros()),
            Phase::Start => {
                // X_C is where the handle rests (on hardware the user has brought it near the
                // centre). A handle resting outside the grid's box (say on a stop below it) is
                // first carried to the grid centre by gliding the field's centre there.
                self.start_time = t;
                let (lo, hi) = (self.plan.origin, self.plan.far_corner());
                let inside = (0..3).all(|a| s.position[a] >= lo[a] && s.position[a] <= hi[a]);
                let (rest_point, glide) = if inside {
                    (s.position, 0.0)
                } else {
                    let centre = self.params.centre;
                    let cells = (centre - s.position).norm() / self.params.spacing;
                    (centre, self.params.move_time * cells.max(1.0))
                };
                self.rest_point = rest_point;
                self.phase = Phase::Init {
                    from: s.position,
                    rest_point,
                    since: t,
                    glide,
                };
                self.emit(CalibrationEvent::InitStarted);
                ControlOutput::force(Vector3::zeros())
            }
            Phase::Init {
                from,
                rest_point,
                since,
                glide,
            } => {
                if t - since > self.params.vertex_timeout + glide {
                    let min_sag = MIN_SAG * self.params.eps_init;
                    return self.fail(match self.init_sag {
                        Some(sag) => CalibrationFailure::NoSag {
                            sag_mm: sag * 1e3,
                            min_mass_g: self.params.k_init * min_sag / self.params.g * 1e3,
                        },
                        None => CalibrationFailure::InitTimeout {
                            timeout: self.params.vertex_timeout,
                        },
                    });
                }
                let centre = if glide > 0.0 {
                    from + (rest_point - from) * minimum_jerk((t - since) / glide)
                } else {
                    rest_point
                };
                let force = (centre - s.position) * self.params.k_init
                    - s.velocity * self.params.init_damping;
                if t - since < glide {
                    return ControlOutput::force(force);
                }
                if let Some(steady) = self.detector.push(&s.position) {
                    let sag = rest_point - steady;
                    // A steady state without sag means something still holds the handle (a hand);
                    // keep waiting for it to be released.
                    self.init_sag = Some(sag.norm());
                    if sag.norm() > MIN_SAG * self.params.eps_init {
                        self.gravity_direction = sag / sag.norm(); // Eq. 7
                        self.initial_mass = self.params.k_init * sag.norm() / self.params.g; // Eq. 8
                        self.initial_steady_state = steady;
                        self.mass = self.initial_mass;
                        self.gain_mass = self.initial_mass; // Eq. 9
                        self.emit(CalibrationEvent::InitDone {
                            gravity_direction: self.gravity_direction,
                            initial_mass: self.initial_mass,
                        });
                        self.vertex = 0;
                        self.start_move(s.position, t);
                        return ControlOutput::force(self.pd_force(&s.position, s));
                    }
                    self.detector.reset();
                }
                ControlOutput::force(force)
            }
            Phase::Move {
                from,
                start,
                duration,
            } => {
                let to = self.plan.path[self.vertex].position;
                let tau = (t - start) / duration;
                let target = from + (to - from) * minimum_jerk(tau);
                if tau >= 1.0 {
                    self.phase = Phase::Hold { since_change: t };
                }
                ControlOutput::force(self.pd_force(&target, s))
            }
            Phase::Hold { since_change } => {
                let vertex = self.plan.path[self.vertex];
                if t - self.vertex_start > self.params.vertex_timeout {
                    return self.fail(CalibrationFailure::VertexTimeout {
                        vertex,
                        timeout: self.params.vertex_timeout,
                        iterations: self.iteration,
                    });
                }
                let force = self.pd_force(&vertex.position, s);
                if t - since_change < self.params.settle_time {
                    return ControlOutput::force(force);
                }
                let Some(steady) = self.detector.push(&s.position) else {
                    // Gains built on a mass several times too large make the hold oscillate
                    // through the velocity filter's lag, and no steady state comes: back off.
                    if t - since_change > self.params.settle_time + GAIN_BACKOFF_AFTER
                        && self.gain_scale > 0.2
                    {
                        self.gain_scale *= 0.5;
                        self.detector.reset();
                        self.phase = Phase::Hold { since_change: t };
                        self.emit(CalibrationEvent::GainsReduced {
                            vertex: self.vertex,
                            scale: self.gain_scale,
                        });
                    }
                    return ControlOutput::force(force);
                };
                // Steady state: k_P (X_i − X̄) + M_j g v_G balances the apparent weight.
                let error = vertex.position - steady;
                // A correct hold settles ΔM g / k_P from the vertex (≈ 9 mm per 100 % mass error at
                // the default gains); half a cell away means the handle is blocked: do not push
                // harder.
                // Likewise when an update did not bring the handle closer: something holds it.
                // Mass updates act along v_G only, so that is the component they must shrink; the
                // offset across v_G (a linkage's horizontal gravity components, or a small error
                // in v_G) stays, and is kept in the holding force for the vector mode.
                let along = error.dot(&self.gravity_direction).abs();
                let stuck = self.iteration >= 1
                    && along > self.params.eps_m
                    && along > 0.8 * self.previous_error;
                self.previous_error = along;
                if error.norm() > 0.5 * self.params.spacing || stuck {
                    return self.fail(CalibrationFailure::Unreachable {
                        vertex,
                        distance_mm: error.norm() * 1e3,
                    });
                }
                let k_p = self
                    .params
                    .gains
                    .stiffness(self.gain_mass * self.gain_scale);
                let holding_force =
                    error * k_p + self.gravity_direction * (self.mass * self.params.g);
                let updated = self.mass + k_p * error.dot(&self.gravity_direction) / self.params.g; // Eq. 11, signed
                self.iteration += 1;
                self.emit(CalibrationEvent::Iteration {
                    vertex: self.vertex,
                    iteration: self.iteration,
                    mass: updated,
                    error: error.norm(),
                });
                if !(updated.is_finite() && updated > 0.0) {
                    return self.fail(CalibrationFailure::NonPositiveMass {
                        vertex,
                        mass: updated,
                    });
                }
                let near = along < self.params.eps_m;
                let converged = near && self.previous_near;
                self.previous_near = near;
                // Gains follow the newest estimate (Eq. 13 lags them by one iteration; see docs).
                self.gain_mass = updated;
                self.gain_scale = 1.0;
                self.mass = updated;
                if converged {
                    self.results[self.vertex] = Some(VertexResult {
                        vertex,
                        mass: updated,
                        force: holding_force,
                        iterations: self.iteration,
                        final_error: error.norm(),
                        duration: t - self.vertex_start,
                    });
                    self.emit(CalibrationEvent::VertexDone {
                        vertex: self.vertex,
                        of: self.plan.path.len(),
                        mass: updated,
                        iterations: self.iteration,
                    });
                    // Eqs. 12, 14: the next vertex starts from M̂(X_i) (already in mass, gain_mass).
                    self.vertex += 1;
                    if self.vertex == self.plan.path.len() {
                        self.phase = Phase::Finished;
                        self.end_time = t;
                        self.emit(CalibrationEvent::Finished);
                        return ControlOutput::done(Vector3::zeros());
                    }
                    self.start_move(vertex.position, t);
                    return ControlOutput::force(self.pd_force(&vertex.position, s));
                }
                if self.iteration >= self.params.max_iterations {
                    return self.fail(CalibrationFailure::TooManyIterations {
                        vertex,
                        iterations: self.iteration,
                    });
                }
                self.detector.reset();
                self.phase = Phase::Hold { since_change: t };
                ControlOutput::force(self.pd_force(&vertex.position, s))
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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

    #[test]
    fn steady_state_needs_two_agreeing_windows_in_the_sphere() {
        let p = |x: f64| Vector3::new(x, 0.0, 0.0);
        let mut d = SteadyState::new(2, 1e-4);
        assert!(d.push(&p(0.0)).is_none());
        assert!(d.push(&p(2e-4)).is_none()); // leaves the sphere: restart here
        assert!(d.push(&p(2e-4)).is_none()); // first window complete: mean 2e-4
        assert!(d.push(&p(2.01e-4)).is_none());
        let mean = d.push(&p(2.01e-4)).unwrap(); // second window 2.01e-4 agrees within 1e-5
        assert!((mean.x - 2.01e-4).abs() < 1e-12);
        // A creeping handle (20 µm between window means, ε/10 = 10 µm) is not steady.
        let mut d = SteadyState::new(2, 1e-4);
        for x in [0.0, 1e-5, 2e-5, 3e-5, 4e-5, 5e-5] {
            assert!(d.push(&p(x)).is_none());
        }
        // An oscillation of ±20 µm over whole windows is.
        let mut d = SteadyState::new(4, 1e-4);
        let wave = [2e-5, -2e-5, 2e-5, -2e-5];
        assert!(wave.iter().map(|&x| d.push(&p(x))).all(|r| r.is_none()));
        assert!(wave
            .iter()
            .map(|&x| d.push(&p(x)))
            .last()
            .unwrap()
            .is_some());
    }
}
