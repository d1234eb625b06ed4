//! The calibration controller: a state machine with one method per phase, which `tick` only
//! dispatches to. Start → Init → (Move → Hold) per vertex → Finished, or Failed from any phase.
//!
//! Like every [`Controller`], it runs on the servo thread: it must not allocate, lock, block or
//! log, so progress leaves through a bounded channel with `try_send`.

use crossbeam_channel::Sender;
use nalgebra::Vector3;

use super::outcome::{CalibrationFailure, CalibrationResult, VertexResult};
use super::plan::{GridPlan, PlanError, Vertex};
use super::steady::SteadyState;
use super::CalibrationParams;
use crate::control::pd::PointHold;
use crate::control::{ControlOutput, Controller, DeviceState};

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

/// The initial steady state must sag more than this many ε_init below X_C (else something still
/// holds the handle): 0.3 mm, the sag of 15 g, with the paper's defaults.
const MIN_SAG: f64 = 3.0;

/// How long a hold may go without a steady state (after the settle time) before the gains are
/// halved, s.
const GAIN_BACKOFF_AFTER: f64 = 1.0;

/// The gains are halved at most three times (1, ½, ¼, ⅛).
const MIN_GAIN_SCALE: f64 = 0.2;

/// Share of the way covered at progress τ ∈ [0, 1] of a minimum-jerk path:
/// s(τ) = 10τ³ − 15τ⁴ + 6τ⁵.
fn minimum_jerk(tau: f64) -> f64 {
    let t = tau.clamp(0.0, 1.0);
    t * t * t * (10.0 - 15.0 * t + 6.0 * t * t)
}

/// A minimum-jerk path from `from` to `to`, `duration` s long from time `start`. The paper steps
/// the set point to the next vertex; a 40 mm step pulls a 120 g handle with 5.4 N at once, and
/// longer moves saturate.
#[derive(Clone, Copy, Debug)]
struct Glide {
    from: Vector3<f64>,
    to: Vector3<f64>,
    start: f64,
    duration: f64,
}

impl Glide {
    /// Progress τ at time `t`; 1 or more once arrived.
    fn progress(&self, t: f64) -> f64 {
        (t - self.start) / self.duration
    }

    /// The point at progress `tau`.
    fn at(&self, tau: f64) -> Vector3<f64> {
        self.from + (self.to - self.from) * minimum_jerk(tau)
    }
}

#[derive(Clone, Copy, Debug)]
enum Phase {
    /// Before the first tick.
    Start,
    /// The initial field holds the handle; its centre glides from the start position to X_C
    /// (`duration` 0: no glide, the handle starts inside the grid's box).
    Init(Glide),
    /// The PD's set point glides to the current vertex.
    Move(Glide),
    /// The PD holds the current vertex; samples count from `since_change` plus the settle time.
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
    /// Device time of the first and of the last tick, s.
    start_time: f64,
    end_time: f64,

    // What the initialisation found.
    /// Unit v_G (Eq. 7).
    gravity_direction: Vector3<f64>,
    /// M̂_0 (Eq. 8), kg.
    initial_mass: f64,
    /// Centre X_C of the initial field, m.
    rest_point: Vector3<f64>,
    /// X(∞), m.
    initial_steady_state: Vector3<f64>,
    /// Sag at the last initial steady state, m.
    init_sag: Option<f64>,

    // The estimates, carried from vertex to vertex (Eqs. 12, 14).
    /// M_j(X_i): the mass in the gravity term.
    mass: f64,
    /// The mass the PD gains are built on: the newest estimate (M̂(X_{i−1}) while moving, Eq. 14).
    gain_mass: f64,
    /// Back-off factor on the gains (1, ½, ¼, ⅛) when a hold finds no steady state.
    gain_scale: f64,

    // The vertex in progress.
    /// Current vertex (index into the plan's path).
    vertex: usize,
    vertex_start: f64,
    /// Mass updates made at this vertex.
    iteration: u32,
    /// Whether the previous steady state at this vertex was within ε_M of it along v_G.
    previous_near: bool,
    /// Offset from the vertex along v_G at the previous steady state, m.
    previous_error: f64,

    /// Per vertex of the path, once done.
    results: Vec<Option<VertexResult>>,
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
            start_time: 0.0,
            end_time: 0.0,
            gravity_direction: Vector3::z(),
            initial_mass: 0.0,
            rest_point: Vector3::zeros(),
            initial_steady_state: Vector3::zeros(),
            init_sag: None,
            mass: 0.0,
            gain_mass: 0.0,
            gain_scale: 1.0,
            vertex: 0,
            vertex_start: 0.0,
            iteration: 0,
            previous_near: false,
            previous_error: f64::INFINITY,
            results: vec![None; count],
        })
    }

    /// The planned grid (vertices, left-out vertices).
    pub fn plan(&self) -> &GridPlan {
        &self.plan
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
                let mut ordered = vec![None; self.results.len()];
                for (k, r) in self.results.iter().enumerate() {
                    ordered[self.plan.grid_index[k]] = *r;
                }
                let vertices = ordered.into_iter().collect::<Option<Vec<VertexResult>>>()?;
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

    /// First tick. X_C is where the handle rests (on hardware the user has brought it near the
    /// centre). A handle resting outside the grid's box (say on a stop below it) is first carried
    /// to the grid centre by gliding the field's centre there.
    fn start(&mut self, s: &DeviceState) -> ControlOutput {
        let t = s.time;
        self.start_time = t;
        let (lo, hi) = (self.plan.origin, self.plan.far_corner());
        let inside = (0..3).all(|a| s.position[a] >= lo[a] && s.position[a] <= hi[a]);
        let field = if inside {
            Glide {
                from: s.position,
                to: s.position,
                start: t,
                duration: 0.0,
            }
        } else {
            let centre = self.params.centre;
            let cells = (centre - s.position).norm() / self.params.spacing;
            Glide {
                from: s.position,
                to: centre,
                start: t,
                duration: self.params.move_time * cells.max(1.0),
            }
        };
        self.rest_point = field.to;
        self.phase = Phase::Init(field);
        self.emit(CalibrationEvent::InitStarted);
        ControlOutput::force(Vector3::zeros())
    }

    /// Initialisation (§3.1): the elastic field k_init (X_C − X), plus damping beyond the paper
    /// (an undamped spring never lets a frictionless handle settle), until a steady state X(∞)
    /// that sags from X_C. A steady state without sag means something still holds the handle (a
    /// hand): keep waiting for it to be released. Samples count only once the glide is over.
    fn initialise(&mut self, s: &DeviceState, field: Glide) -> ControlOutput {
        let t = s.time;
        if t - field.start > self.params.vertex_timeout + field.duration {
            return self.fail(self.init_failure());
        }
        let centre = if field.duration > 0.0 {
            field.at(field.progress(t))
        } else {
            field.to
        };
        let force =
            (centre - s.position) * self.params.k_init - s.velocity * self.params.init_damping;
        if t - field.start < field.duration {
            return ControlOutput::force(force);
        }
        if let Some(steady) = self.detector.push(&s.position) {
            let sag = field.to - steady;
            self.init_sag = Some(sag.norm());
            if sag.norm() > MIN_SAG * self.params.eps_init {
                self.found_gravity(steady, sag);
                self.vertex = 0;
                self.start_move(s.position, t);
                return ControlOutput::force(self.pd_force(&s.position, s));
            }
            self.detector.reset();
        }
        ControlOutput::force(force)
    }

    /// Why the initialisation gave up: it found a steady state that did not sag, or none at all.
    fn init_failure(&self) -> CalibrationFailure {
        match self.init_sag {
            Some(sag) => CalibrationFailure::NoSag {
                sag_mm: sag * 1e3,
                min_mass_g: self.params.k_init * (MIN_SAG * self.params.eps_init) / self.params.g
                    * 1e3,
            },
            None => CalibrationFailure::InitTimeout {
                timeout: self.params.vertex_timeout,
            },
        }
    }

    /// Eqs. 7–9 from the initial steady state X(∞) and its sag X_C − X(∞): v_G along the sag,
    /// M̂_0 = k_init ‖sag‖ / g, and the first gains built on M̂_0.
    fn found_gravity(&mut self, steady: Vector3<f64>, sag: Vector3<f64>) {
        self.gravity_direction = sag / sag.norm(); // Eq. 7
        self.initial_mass = self.params.k_init * sag.norm() / self.params.g; // Eq. 8
        self.initial_steady_state = steady;
        self.mass = self.initial_mass;
        self.gain_mass = self.initial_mass; // Eq. 9
        self.emit(CalibrationEvent::InitDone {
            gravity_direction: self.gravity_direction,
            initial_mass: self.initial_mass,
        });
    }

    /// Set off from `from` toward the current vertex, with a fresh vertex record.
    fn start_move(&mut self, from: Vector3<f64>, t: f64) {
        let to = self.plan.path[self.vertex].position;
        let cells = (to - from).norm() / self.params.spacing;
        self.phase = Phase::Move(Glide {
            from,
            to,
            start: t,
            duration: self.params.move_time * cells.max(1.0),
        });
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

    /// Move (§3.2): the PD (with the gravity term of the mass so far) follows the glide to the
    /// vertex, then holds it.
    fn move_to_vertex(&mut self, s: &DeviceState, path: Glide) -> ControlOutput {
        let tau = path.progress(s.time);
        if tau >= 1.0 {
            self.phase = Phase::Hold {
                since_change: s.time,
            };
        }
        ControlOutput::force(self.pd_force(&path.at(tau), s))
    }

    /// Hold (§3.2): the PD holds the vertex with the gravity term M_j g v_G (Eq. 10). Each steady
    /// state after the settle time gives a mass update; a hold without a steady state backs off
    /// its gains.
    fn hold(&mut self, s: &DeviceState, since_change: f64) -> ControlOutput {
        let t = s.time;
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
        match self.detector.push(&s.position) {
            Some(steady) => self.update_mass(s, vertex, steady),
            None => {
                if t - since_change > self.params.settle_time + GAIN_BACKOFF_AFTER
                    && self.gain_scale > MIN_GAIN_SCALE
                {
                    self.back_off(t);
                }
                ControlOutput::force(force)
            }
        }
    }

    /// Halve k_P and k_D (not the gravity term): gains built on a mass several times too large
    /// make the hold oscillate through the velocity filter's lag, and no steady state comes. The
    /// next mass update restores them.
    fn back_off(&mut self, t: f64) {
        self.gain_scale *= 0.5;
        self.detector.reset();
        self.phase = Phase::Hold { since_change: t };
        self.emit(CalibrationEvent::GainsReduced {
            vertex: self.vertex,
            scale: self.gain_scale,
        });
    }

    /// A steady state X̄ at `vertex` X_i: there k_P (X_i − X̄) + M_j g v_G balances the apparent
    /// weight, so the mass is updated with the *signed* Eq. 11,
    /// M_{j+1} = M_j + k_P (X_i − X̄)·v_G / g (the paper's norm loses the sign, and a mass that is
    /// too large then grows without end), and that whole holding force is kept for the vector
    /// mode.
    ///
    /// The vertex ends at the second consecutive steady state within ε_M of it along v_G (the only
    /// direction a mass update moves the handle): its last update is then measured at the vertex,
    /// after a transient too small to bias it. The offset across v_G (a linkage's horizontal
    /// gravity components, or a small error in v_G) stays, in the holding force.
    fn update_mass(
        &mut self,
        s: &DeviceState,
        vertex: Vertex,
        steady: Vector3<f64>,
    ) -> ControlOutput {
        let t = s.time;
        let error = vertex.position - steady;
        // A correct hold settles ΔM g / k_P from the vertex (≈ 9 mm per 100 % mass error at the
        // default gains); half a cell away means the handle is blocked: do not push harder.
        // Likewise when an update did not bring the handle closer along v_G: something holds it.
        let along = error.dot(&self.gravity_direction).abs();
        let stuck =
            self.iteration >= 1 && along > self.params.eps_m && along > 0.8 * self.previous_error;
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
        let holding_force = error * k_p + self.gravity_direction * (self.mass * self.params.g);
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
        // Unlike Eq. 13 (k_P(i,j) = β M_{j−1}), the gains follow the newest estimate: lagged
        // gains leave the loop mis-linearised for a whole iteration after a large correction.
        self.gain_mass = updated;
        self.gain_scale = 1.0;
        self.mass = updated;
        if converged {
            return self.vertex_done(
                s,
                VertexResult {
                    vertex,
                    mass: updated,
                    force: holding_force,
                    iterations: self.iteration,
                    final_error: error.norm(),
                    duration: t - self.vertex_start,
                },
            );
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

    /// Record the vertex and go on to the next one, which starts from this one's mass
    /// M̂(X_i) (Eqs. 12, 14; already in `mass` and `gain_mass`), or finish.
    fn vertex_done(&mut self, s: &DeviceState, result: VertexResult) -> ControlOutput {
        self.results[self.vertex] = Some(result);
        self.emit(CalibrationEvent::VertexDone {
            vertex: self.vertex,
            of: self.plan.path.len(),
            mass: result.mass,
            iterations: result.iterations,
        });
        self.vertex += 1;
        if self.vertex == self.plan.path.len() {
            self.phase = Phase::Finished;
            self.end_time = s.time;
            self.emit(CalibrationEvent::Finished);
            return ControlOutput::done(Vector3::zeros());
        }
        let here = result.vertex.position;
        self.start_move(here, s.time);
        ControlOutput::force(self.pd_force(&here, s))
    }

    fn fail(&mut self, failure: CalibrationFailure) -> ControlOutput {
        self.phase = Phase::Failed(failure);
        self.emit(CalibrationEvent::Failed(failure));
        ControlOutput::done(Vector3::zeros())
    }

    fn emit(&self, event: CalibrationEvent) {
        if let Some(tx) = &self.events {
            let _ = tx.try_send(event);
        }
    }

    /// The feedback-linearised PD toward `target` with gains on the newest mass (backed off by
    /// `gain_scale`) plus the gravity term M_j g v_G (Eq. 10).
    fn pd_force(&self, target: &Vector3<f64>, s: &DeviceState) -> Vector3<f64> {
        let gravity = self.gravity_direction * (self.mass * self.params.g);
        self.params
            .gains
            .pd_force(self.gain_mass * self.gain_scale, target, s, &gravity)
    }
}

impl Controller for Calibration {
    fn tick(&mut self, s: &DeviceState) -> ControlOutput {
        match self.phase {
            Phase::Start => self.start(s),
            Phase::Init(field) => self.initialise(s, field),
            Phase::Move(path) => self.move_to_vertex(s, path),
            Phase::Hold { since_change } => self.hold(s, since_change),
            Phase::Finished | Phase::Failed(_) => ControlOutput::done(Vector3::zeros()),
        }
    }
}
