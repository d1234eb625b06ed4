//! The calibration controller: a state machine with one method per phase, which `tick` only
//! dispatches to. Start → Catch → InitBand (x, y, z) → (Recentre → Pulse) per axis → Recentre →
//! InitStrokes → (Move → Settle ⇄ Band / Push → Strokes) per vertex → Finished, or Failed from
//! any phase. Under friction, a vertex whose force the vertices measured before it predict
//! ([`Calibration::predicted_force`]) goes from Move straight to Strokes; with a
//! [`super::Prior`] (`hgcd check`) the initialisation ends at Catch and every vertex does.
//!
//! Like every [`Controller`], it runs on the servo thread: it must not allocate, lock, block or
//! log, so progress leaves through a bounded channel with `try_send`.

use crossbeam_channel::Sender;
use nalgebra::{Matrix3, Vector3};

use super::explore::{self, Explorer};
use super::outcome::{
    CalibrationFailure, CalibrationResult, InitialMeasurement, TimeSpent, VertexResult,
};
use super::plan::{GridPlan, PlanError, Vertex};
use super::predict::ArmPrediction;
use super::probe::{BandProbe, Pulse, Push, Ramp, Smoother, Step, Stroke, Stroked, Strokes};
use super::steady::{NoiseMeter, SteadyState};
use super::CalibrationParams;
use crate::config::WorkspaceMode;
use crate::control::pd::{AxisGains, PointHold};
use crate::control::{ControlOutput, Controller, DeviceState};
use crate::estimate::Foaw;
use crate::fit::lattice;

/// Progress, sent with `try_send` from the servo thread.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum CalibrationEvent {
    InitStarted,
    /// What the initialisation measured at X_C: the load's direction and |load| / g, the
    /// friction (stick band half-widths) and the moving mass along x, y, z.
    InitDone {
        gravity_direction: Vector3<f64>,
        initial_mass: f64,
        friction: Vector3<f64>,
        inertia: Vector3<f64>,
    },
    /// The move to a vertex began (again, for a vertex approached a second time), `elapsed` s
    /// of device time into the run.
    VertexStarted {
        vertex: usize,
        of: usize,
        at: Vertex,
        elapsed: f64,
    },
    /// The force estimate at a vertex changed: after a rest off the vertex, or a round of band
    /// measurements. `error` is the distance of that rest from the vertex, m.
    Iteration {
        vertex: usize,
        iteration: u32,
        force: Vector3<f64>,
        error: f64,
    },
    /// No steady state came at a hold: the gains were scaled by `scale`.
    GainsReduced {
        vertex: usize,
        scale: f64,
    },
    /// The vertex could not be measured (as in `VertexUnreachable`): it is approached again,
    /// by way of the point `beside` it.
    VertexRetried {
        vertex: usize,
        at: Vertex,
        failure: Option<CalibrationFailure>,
        beside: Vector3<f64>,
    },
    /// `mass` is the force along the load direction found at X_C, over g (the final v_G comes
    /// from every vertex's force).
    VertexDone {
        vertex: usize,
        of: usize,
        mass: f64,
        force: Vector3<f64>,
        iterations: u32,
        /// Device time since the run began, s.
        elapsed: f64,
    },
    /// The vertex could not be measured, twice on a cube (`retried`), once in an explored
    /// workspace: the handle did not yield to a push toward it (`failure` None), or did not
    /// converge there (`failure`). It stays `distance` m away; its values are filled from its
    /// neighbours.
    VertexUnreachable {
        vertex: usize,
        of: usize,
        at: Vertex,
        distance: f64,
        failure: Option<CalibrationFailure>,
        retried: bool,
        /// Device time since the run began, s.
        elapsed: f64,
    },
    /// Exploration: move `probe` (counted from 0) went `run` m from the vertex at `from` along
    /// the axis `direction` toward its neighbour, and met a stop (`stopped`) or arrived.
    Probed {
        probe: usize,
        from: Vector3<f64>,
        direction: Vector3<f64>,
        run: f64,
        stopped: bool,
    },
    /// Exploration is over: `probes` moves, `stopped` of them on a stop, `reached` vertices
    /// reached; the grid has `vertices` vertices to calibrate and `extrapolated` outside the
    /// explored workspace or too near its stops.
    Explored {
        probes: usize,
        stopped: usize,
        reached: usize,
        vertices: usize,
        extrapolated: usize,
        dims: [usize; 3],
    },
    Finished,
    Failed(CalibrationFailure),
}

/// The friction at X_C, N, from which vertices are predicted and measured by their strokes
/// alone: there the bands take 3–4 s a vertex. Below it the run is the paper's (Eq. 12, rests,
/// bands): the simulated PHANToM with frictionless joints reads 0.014–0.024 N at X_C (the bands'
/// own lag), and started from predictions its rests and bands left a vertex 2.1 % off
/// vertically where they leave 1.9 %; with 0.02 N at the handle it reads 0.03 N or more.
const STROKES_AT_ONCE: f64 = 0.03;
/// A vertex within this share of the spacing of a lattice point is at it (a prediction's
/// stencil).
const PREDICT_MATCH: f64 = 1e-3;
/// The largest stencil a prediction is made from: the sum of its three vertices' distances to
/// the vertex predicted, in spacings (a cell's parallelogram: 1 + 1 + √2; a straight line
/// through two neighbours: 1 + 1 + 2). The corners' cube's faces (2 + 2 + 2√2) predict the
/// fourth corner 30 mN or more off on the simulated linkages: their strokes ran twice.
const PREDICT_REACH: f64 = 4.0;
/// Smallest displacement of the smoothed position that counts as a slip, m (on top of three
/// standard deviations of the measured position noise).
const MIN_SLIP: f64 = 5e-6;
/// … and at least this many encoder steps.
const SLIP_STEPS: f64 = 1.25;
/// Hold offset the friction band may span at most, m, or this many encoder steps if more: the
/// hold stiffens until it does (within the bandwidth bound below), but not so far that one step
/// of the reading is a large force.
const FRICTION_OFFSET: f64 = 2e-4;
const FRICTION_OFFSET_STEPS: f64 = 10.0;
/// Largest natural frequency of the hold, in radians per report period.
const MAX_OMEGA_PERIODS: f64 = 0.25;
/// Share of `safety.max_force_n` calibration pushes with, beyond the forces it holds.
const PUSH_SHARE: f64 = 0.25;

/// How far outside the declared workspace box a handle may rest when calibration starts: this
/// share of the box's half-extent along each axis, and at least [`WORKSPACE_SLACK_MIN`] (a
/// handle resting on a stop just beyond a box drawn inside the stops). Further out, the box
/// and the device disagree: nothing is pushed.
const WORKSPACE_SLACK_SHARE: f64 = 0.25;
const WORKSPACE_SLACK_MIN: f64 = 0.02;

/// Until the handle has moved this far from where it rested, m, the field that catches it (and
/// carries it to the grid) pushes with at most [`CARRY_SHARE`] of the force limit: enough to lift
/// a handle of up to that weight, well below what a stuck handle would otherwise be pushed with.
const SEEN_MOVING: f64 = 0.005;
const CARRY_SHARE: f64 = 0.5;
/// The moving-mass pulse: distance timed, m; time limit, s; least force beyond the band, N.
const PULSE_DISTANCE: f64 = 5e-4;
const PULSE_TIMEOUT: f64 = 0.5;
const PULSE_MIN_EXCESS: f64 = 0.05;
const PULSE_LOAD_SHARE: f64 = 0.1;
/// A ramp of added force starts slow enough to cross the measured band in this time, s …
const CROSSING_TIME: f64 = 0.15;
/// … and to move a frictionless handle by a slip in this time, s …
const DETECT_TIME: f64 = 0.03;
/// … and its rate grows by e every this many seconds (init: the band is still unknown).
const RAMP_GROWTH: f64 = 0.3;
/// At X_C the ramp is steady at least at this rate, N/s, over this much force, N.
const INIT_RAMP_RATE: f64 = 0.1;
const INIT_RAMP_STEADY: f64 = 0.5;
const INIT_RAMP_GROWTH: f64 = 0.15;
/// An axis counts as frictionless when its band at X_C is no wider than a frictionless handle's
/// seems, and as dominated by friction (its hold at rest then needs no velocity feedback) when
/// it is more than twice as wide, plus this much, N.
const DOMINANT_FLOOR: f64 = 0.005;
const DOMINANT_BANDS: f64 = 1.5;

/// What the stick band at X_C says about the friction along an axis.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Friction {
    /// No wider than a frictionless handle's seems: there the force the hold applies at rest is
    /// the load, and no band is measured at vertices.
    None,
    /// Wider: bands are measured with the hold's velocity feedback on, and checked.
    Slight,
    /// More than twice as wide: it dissipates more than the velocity feedback would, so the
    /// hold measures bands without it (its noise would shake the stuck handle).
    Dominant,
}
/// The reach tolerance: this many friction-band offsets, plus three noise standard deviations,
/// plus this margin, m.
const REACH_BANDS: f64 = 2.5;
const REACH_MARGIN: f64 = 2e-5;
/// Rounds of band measurements at one vertex, at least and at most; once a round changes the
/// force by less than this share of the band plus this much, the vertex ends (N).
const MIN_ROUNDS: u32 = 2;
const MAX_ROUNDS: u32 = 3;
/// The three constraint normals must span at least this volume (1 for orthogonal ones).
const MIN_CONSTRAINT_VOLUME: f64 = 0.3;
/// A band's slips show joint friction when the difference of their directions is more than 25°
/// off its push (a ball of friction's follows it wherever the chord crosses): cos below this.
const ALONG_PUSH: f64 = 0.906;
/// Two normals within 20° of each other (|cos| above this) belong to the same pair of faces (a
/// linkage's joints move the handle along directions further apart: the delta's come within
/// 34° at the corners of its cube).
const SAME_FACES: f64 = 0.94;
/// Another round is measured where the handle is if it is within this many reach tolerances of
/// the vertex; further off, it settles again first.
const ROUND_REACH: f64 = 4.0;
const ROUND_SHARE: f64 = 0.1;
const FORCE_TOLERANCE: f64 = 1e-3;
/// Window means at a vertex rest agree within this many standard deviations of their noise,
/// and at least this much, m.
const CREEP_SIGMAS: f64 = 4.0;
const MIN_CREEP: f64 = 1e-6;
/// Settle time after a change, in radians of the slowest axis (7/ω ≈ two rise times at ζ = 1).
const SETTLE_RADIANS: f64 = 7.0;
/// An update that leaves the handle further than this share of its previous offset did not
/// help: push toward the vertex.
const PROGRESS: f64 = 0.8;

/// Sliding friction along an axis beyond this at the survey's strokes is friction the bands may
/// have missed, N: a frictionless handle's passes differ by a fraction of a millinewton, and
/// viscous damping up to 1 N·s/m (which holds nothing at rest and needs no band) adds at most
/// 4 mN at their 4 mm/s.
const STROKE_FRICTION: f64 = 0.005;
/// A feedforward further than this from the load is more than strokes take without a second
/// look: the survey's bands at X_C are measured again, a hold held off by that much is a stop or
/// a wrong F̂, N.
const STROKE_REPEAT: f64 = 0.03;
/// Strokes that moved F̂ by more than `STROKE_REPEAT` and this share of the force they found
/// are measured once more, from there. On the simulated delta, whose bands at its lower corners
/// left F̂ 0.13–0.39 N off (of 0.75 N), the second strokes moved it by 1.1–1.9 mN (0.15–0.25 %);
/// after an F̂ 0.086 N off (of 0.91 N), by 1.2 mN, for 9 s of device time. On the PHANToM's
/// 65–130 mN the floor, 30 mN, decides. (`CalibrationParams::strokes_again_share`.)
pub(super) const STROKES_AGAIN_SHARE: f64 = 0.1;
/// The survey strokes at X_C send the initialisation back at most this many times: a band read
/// its axis's friction under this share of the strokes' sliding friction, or the hold did not
/// carry the handle through them. On the simulated PHANToM with a 0.1 N band, misread bands read
/// 0–35 % of the sliding friction, sound ones 105–130 %.
const INIT_REMEASURES: u32 = 2;
const MISREAD_SHARE: f64 = 0.5;
/// Share of the hold's damping strokes keep along axes where friction dominates: a sliding
/// joint's friction damps the hold there, and the velocity feedback's noise, multiplied by the
/// full damping, shakes the joints so that the passes' windows no longer cancel their friction.
/// On the simulated PHANToM with 1.54 times its published joint friction (a 0.1 N band at the
/// handle), full damping (ζ = 1) left vertices 3–9 % off vertically, a quarter of it within
/// 1 %; none at all leaves the handle ringing along the strokes (2–3 %).
const STROKE_DAMPING: f64 = 0.25;

/// Speed above which a still hold damps and pulls on the raw position, m/s. The still hold's
/// spring on a smoothed position, undamped, lags the handle by some 4 ms: at 150 rad/s that is
/// a negative damping only the friction absorbs, and it absorbs less than the lag feeds in
/// once the handle rings by more than about 0.1 mm. On the simulated WoodenHaptics arm (unit
/// 2, 0.02 N at the handle, a band at X_C read 0.17 N wide, so ω ≈ 150 rad/s along x) a slip
/// set the hold ringing and the ring grew to a 0.3 m excursion onto a joint stop. A handle at
/// rest reads well under this speed (the chatter limit at X_C is 2 mm/s); a slip passes it.
const RINGING_SPEED: f64 = 0.01;

/// How long a hold may go without a steady state (after the settle time) before the gains are
/// halved, s.
const GAIN_BACKOFF_AFTER: f64 = 1.0;

/// A handle whose velocity keeps a root mean square above this at a steady state of the initial
/// field chatters (m/s): its damping is too strong for it.
const CHATTER_SPEED: f64 = 2e-3;
/// A reading that flickers by one encoder step q between ticks reads as speed in the velocity
/// filter's short windows: about q over this time in root mean square (s). On the simulated
/// WoodenHaptics arm, frictionless and at rest in the initial field, its 43–50 µm steps read
/// 7–14 mm/s; at the point mass's 5 µm this is `CHATTER_SPEED`. Speed up to q / `FLICKER_TIME` is
/// no chatter: halving the damping for it left the frictionless arm ringing.
const FLICKER_TIME: f64 = 2.5e-3;
/// A handle at rest on joint encoders reads within about one step of each joint: the initial
/// field's steady state asks its samples within this many steps, where ε_init is tighter.
const STEADY_STEPS: f64 = 3.0;

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
pub(super) struct Glide {
    pub(super) from: Vector3<f64>,
    pub(super) to: Vector3<f64>,
    pub(super) start: f64,
    pub(super) duration: f64,
}

impl Glide {
    /// Progress τ at time `t`; 1 or more once arrived.
    pub(super) fn progress(&self, t: f64) -> f64 {
        if self.duration > 0.0 {
            (t - self.start) / self.duration
        } else {
            1.0
        }
    }

    /// The point at time `t`.
    pub(super) fn at(&self, t: f64) -> Vector3<f64> {
        self.from + (self.to - self.from) * minimum_jerk(self.progress(t))
    }
}

#[derive(Clone, Copy, Debug)]
enum Phase {
    /// Before the first tick.
    Start,
    /// The initial field catches the handle; its centre glides from the start position to X_C
    /// (`duration` 0: no glide, the handle starts inside the grid's box).
    Catch(Glide),
    /// The stick band along one axis at X_C, under the initial field.
    InitBand(BandProbe),
    /// The initial field, now with the measured load as its gravity term, brings the handle back
    /// to X_C; then the moving-mass pulse along `axis` (3: the initialisation is over) with
    /// `excess` N beyond the band.
    Recentre {
        axis: usize,
        excess: f64,
        since: f64,
    },
    Pulse(Pulse),
    /// The PD's set point glides to the current vertex; `walked`: along an edge the
    /// exploration's walk travelled end to end (nothing in the way). A second attempt at a
    /// vertex goes by way of other points first: `then`, the points still to glide to.
    Move {
        path: Glide,
        walked: bool,
        then: [Option<Vector3<f64>>; 2],
    },
    /// The PD holds the current vertex; samples count from `since` plus the settle time.
    Settle {
        since: f64,
    },
    /// The stick band along one axis at the current vertex; `round_start` is the force
    /// estimate when this round of three axes began; the hold's set point is `anchor`, where
    /// the handle rested when this axis began, so that the force on the other axes is the
    /// estimate itself.
    Band {
        probe: BandProbe,
        round_start: Vector3<f64>,
        anchor: Vector3<f64>,
    },
    /// A growing push toward the vertex: friction yields to it, an obstacle does not.
    Push(Push),
    /// The last check at a vertex: the hold, centred where the handle rests, applies the band's
    /// middle. A frictional handle stays; a frictionless one (whose "band" is only the slip
    /// detection's dynamics) moves to where the force it then gets is its load.
    Check {
        anchor: Vector3<f64>,
        since: f64,
    },
    /// Strokes through X_C, once the hold's gains are built: the friction they find along each
    /// axis tells a frictional axis from one whose stick band at X_C was only the slip
    /// detection's lag, which the bands alone cannot do near a coarse encoder's step.
    InitStrokes(Strokes),
    /// The probes of the reachable workspace from X_C (`calibration.workspace = "explore"`),
    /// run by the calibration's [`Explorer`].
    Explore,
    /// Strokes through the vertex along three diagonals, one way and back, whose mean force is
    /// the vertex's holding force (friction cancels between the passes).
    Strokes {
        strokes: Strokes,
        run: StrokeRun,
    },
    Finished,
    Failed(CalibrationFailure),
}

/// What a vertex's strokes carry from one attempt to the next.
#[derive(Clone, Copy, Debug)]
struct StrokeRun {
    /// Distance from the vertex of the rest the bands were measured at, m.
    error: f64,
    /// The failure to report if the strokes are blocked after the vertex ran out of time.
    late: Option<CalibrationFailure>,
    /// Whether a result that moves F̂ by more than `STROKE_REPEAT` (or `STROKES_AGAIN_SHARE` of
    /// the force) is measured once more.
    repeat: bool,
    /// The bands' F̂ while blocked strokes run again from the force that holds the handle where
    /// it rests: a second block puts it back (that force may be a stop's reaction).
    bands_force: Option<Vector3<f64>>,
}

impl StrokeRun {
    fn first(error: f64, late: Option<CalibrationFailure>) -> Self {
        Self {
            error,
            late,
            repeat: true,
            bands_force: None,
        }
    }
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
    /// The face normals the bands followed at the last vertex measured.
    last_normals: [Vector3<f64>; 3],
    /// Where the handle rested at the first tick, m, and whether it has moved since
    /// ([`SEEN_MOVING`]).
    rested_at: Vector3<f64>,
    followed: bool,
    /// Whether the current vertex is being approached a second time, and where its first
    /// approach started, m.
    retried: bool,
    approach: Vector3<f64>,
    /// Every reading of the initialisation, for the encoder's step once the handle has moved.
    moving: NoiseMeter,
    /// Device time of the last tick, s, and where the time went so far.
    last_tick: Option<f64>,
    time_spent: TimeSpent,

    // What the initialisation found.
    /// Centre X_C of the initial field, m.
    rest_point: Vector3<f64>,
    /// Gravity term of the initial field: zero while catching, the load once measured, N.
    catch_force: Vector3<f64>,
    /// Back-off factor on the initial field's damping, and when it last changed, s.
    field_scale: f64,
    field_since: f64,
    /// Mean square of the velocity lately while the initial field holds the handle, m²/s².
    speed_square: f64,
    initial: InitialMeasurement,
    /// Displacement of the smoothed position that counts as a slip, m, and how far a single
    /// reading may lie from where the handle stuck before it counts as moving, m.
    slip: f64,
    still: f64,
    /// The position noise, measured at the initialisation's rests, m.
    noise: NoiseMeter,
    /// The velocity estimate every force here uses: the servo loop's filter, its noise bound
    /// raised to the encoder step once that is measured (a single step would otherwise read as
    /// a burst of speed, and the damping would kick a resting handle with it).
    filter: Foaw,
    /// Its noise bound, m.
    filter_bound: f64,
    /// The hold's gains and the settle time they need, s.
    gains: AxisGains,
    settle_time: f64,

    // The estimates, carried from vertex to vertex (Eqs. 12, 14).
    /// F̂: the force estimate the hold applies as its gravity term, N.
    estimate: Vector3<f64>,
    /// The force of the last vertex reached (the load at X_C before the first), N.
    last_good: Vector3<f64>,
    /// Back-off factor on the gains (1, ½, ¼, ⅛) when a hold finds no steady state.
    gain_scale: f64,
    /// The friction along each axis, as the initialisation found it. Along axes it dominates,
    /// the hold at rest needs no velocity feedback and pulls on the smoothed position.
    friction_kind: [Friction; 3],
    /// Whether the bands' slips teach the stick region's face normals, or the bands stay along
    /// the axes: from the first band whose slips' difference went more than 25° off its push
    /// (joint friction: the handle moves along the joint that gives), where every axis has
    /// friction.
    learn_normals: bool,

    /// The normals of the stick region's three pairs of faces, as the last round found them
    /// (the axes until then), carried from vertex to vertex: each round's bands go along their
    /// dual directions. For joint friction they are the directions the joints move the handle
    /// along (the Jacobian's columns), which turn slowly over the workspace.
    normals: [Vector3<f64>; 3],
    /// Half the distance between each pair of faces along its normal, N.
    faces: Vector3<f64>,
    smoother: Smoother,
    smoothed: Vector3<f64>,

    // The vertex in progress.
    /// Current vertex (index into the plan's path).
    vertex: usize,
    /// When the vertex's time limit started: its first approach's arrival, or a retry's.
    vertex_start: f64,
    /// When its first move began, for the device time it cost (retry included).
    vertex_began: f64,
    /// Updates of the force estimate at this vertex, and rounds of band measurements.
    iteration: u32,
    rounds: u32,
    /// Distance from the vertex of the previous rest off it, m.
    previous_offset: Option<f64>,
    /// Rests near the vertex so far.
    near_rests: u32,
    /// The force at the first rest near the vertex (the paper's one-sided measurement), N.
    one_sided: Option<Vector3<f64>>,
    /// The rest the band is measured at, m, and the band's half-widths, N.
    rest: Vector3<f64>,
    band_friction: Vector3<f64>,
    /// The current vertex's F̂ starts from a prediction under friction (the saved model's, with a
    /// [`super::Prior`], or the measured vertices', [`Calibration::predicted_force`]): the strokes
    /// measure at once, without rests or bands.
    strokes_at_once: bool,
    /// With an arm profile, the arm's gravity fitted to the vertices measured so far: it
    /// predicts the next ([`Calibration::predicted_force`]).
    arm_fit: Option<ArmPrediction>,
    /// The force the previous round found, when this round followed it directly.
    /// The forces the rounds before this one found, summed, and how many, when this round
    /// followed them directly.
    earlier_rounds: (Vector3<f64>, Vector3<f64>, u32),
    /// Where each band of the round was measured ([`Band::at`]), and where the vertex's force
    /// was measured (the mean over the bands, and over the rounds averaged), m.
    band_at: [Vector3<f64>; 3],
    measured_at: Vector3<f64>,
    /// The round's constraints on the holding force, one per band ([`Band::constraint`]), and
    /// the directions its slips went ([`Band::slips`]).
    constraints: [Option<(Vector3<f64>, f64)>; 3],
    /// The bands' constraints across one pair of faces each, whatever the mode.
    strict: [Option<(Vector3<f64>, f64)>; 3],
    /// Whether a band's slips have gone off its push (joint friction).
    joint_friction: bool,
    /// How many times the survey strokes at X_C sent the initialisation back to measure again
    /// ([`Calibration::init_strokes`]).
    init_remeasured: u32,
    slips: [[Option<Vector3<f64>>; 2]; 3],

    /// Per vertex of the path, once done (reached or not).
    results: Vec<Option<VertexResult>>,
    /// The probes of an exploring calibration (built before the run).
    explorer: Option<Explorer>,
}

impl Calibration {
    pub fn new(
        params: CalibrationParams,
        events: Option<Sender<CalibrationEvent>>,
    ) -> Result<Self, PlanError> {
        let mut plan = GridPlan::new(&params)?;
        let count = plan.path.len();
        let mut results = vec![None; count];
        let explorer = (params.workspace_mode == WorkspaceMode::Explore).then(|| {
            plan.reserve_explored();
            results.reserve(plan.path.capacity());
            Explorer::new(
                params.workspace,
                params.spacing,
                PUSH_SHARE * params.max_force,
            )
        });
        let n_init = params.n_init;
        let arm_fit = params.arm.map(|arm| ArmPrediction::new(arm, params.g));
        let filter_bound = params.noise_bound;
        let filter = Foaw::new(
            params.foaw_variant,
            params.noise_bound,
            params.max_window,
            params.period,
        )
        .map_err(PlanError::Filter)?;
        Ok(Self {
            detector: SteadyState::new(params.n_init, params.eps_init),
            params,
            plan,
            events,
            phase: Phase::Start,
            start_time: 0.0,
            end_time: 0.0,
            last_normals: [0, 1, 2].map(axis),
            rested_at: Vector3::zeros(),
            followed: false,
            retried: false,
            approach: Vector3::zeros(),
            moving: NoiseMeter::new(n_init),
            last_tick: None,
            time_spent: TimeSpent::default(),
            rest_point: Vector3::zeros(),
            catch_force: Vector3::zeros(),
            field_scale: 1.0,
            field_since: 0.0,
            speed_square: 0.0,
            initial: InitialMeasurement {
                load: Vector3::zeros(),
                friction: Vector3::zeros(),
                inertia: Vector3::zeros(),
                noise: 0.0,
                step: 0.0,
                stiffness: Vector3::zeros(),
            },
            slip: MIN_SLIP,
            still: 0.0,
            noise: NoiseMeter::new(n_init),
            filter_bound,
            filter,
            gains: AxisGains {
                stiffness: Vector3::zeros(),
                damping: Vector3::zeros(),
            },
            settle_time: 0.0,
            estimate: Vector3::zeros(),
            last_good: Vector3::zeros(),
            gain_scale: 1.0,
            friction_kind: [Friction::None; 3],
            smoother: Smoother::new(),
            smoothed: Vector3::zeros(),
            vertex: 0,
            vertex_start: 0.0,
            vertex_began: 0.0,
            iteration: 0,
            rounds: 0,
            previous_offset: None,
            near_rests: 0,
            one_sided: None,
            rest: Vector3::zeros(),
            band_friction: Vector3::zeros(),
            strokes_at_once: false,
            arm_fit,
            constraints: [None; 3],
            strict: [None; 3],
            joint_friction: false,
            init_remeasured: 0,
            slips: [[None; 2]; 3],
            learn_normals: false,

            normals: [0, 1, 2].map(axis),
            faces: Vector3::zeros(),
            earlier_rounds: (Vector3::zeros(), Vector3::zeros(), 0),
            band_at: [Vector3::zeros(); 3],
            measured_at: Vector3::zeros(),
            results,
            explorer,
        })
    }

    /// The planned grid (vertices, left-out vertices).
    pub fn plan(&self) -> &GridPlan {
        &self.plan
    }

    /// After a successful run: the hold at the last vertex reached (its gains and the force it
    /// measured there), to keep the handle up until the new grid is in use.
    pub fn final_hold(&self) -> Option<PointHold> {
        if !matches!(self.phase, Phase::Finished) {
            return None;
        }
        let last = self.results.iter().rev().flatten().find(|r| r.reached)?;
        Some(PointHold {
            set_point: last.vertex.position,
            force: last.force,
            gains: self.gains,
        })
    }

    /// The result once finished, the failure if it failed, None while running (or if aborted).
    /// Completes the lattice ([`lattice::complete`]: v_G, the vertices not reached), so call it
    /// off the servo thread.
    pub fn outcome(&self) -> Option<Result<CalibrationResult, CalibrationFailure>> {
        match self.phase {
            Phase::Failed(f) => Some(Err(f)),
            Phase::Finished => Some(Ok(self.result()?)),
            _ => None,
        }
    }

    fn result(&self) -> Option<CalibrationResult> {
        let mut ordered = vec![None; self.plan.vertex_count()];
        for (k, r) in self.results.iter().enumerate() {
            ordered[self.plan.grid_index[k]] = *r;
        }
        for &(vertex, flat) in &self.plan.extrapolated {
            ordered[flat] = Some(VertexResult {
                vertex,
                mass: 0.0,
                force: Vector3::zeros(),
                held_force: Vector3::zeros(),
                one_sided_force: Vector3::zeros(),
                friction: Vector3::zeros(),
                iterations: 0,
                final_error: 0.0,
                measured_at: vertex.position,
                duration: 0.0,
                reached: false,
                failure: None,
            });
        }
        let mut vertices = ordered.into_iter().collect::<Option<Vec<VertexResult>>>()?;
        let load = self.initial.load;
        let known: Vec<bool> = vertices.iter().map(|v| v.reached).collect();
        let offsets: Vec<Vector3<f64>> = vertices
            .iter()
            .map(|v| v.vertex.position - v.measured_at)
            .collect();
        let mut forces: Vec<Vector3<f64>> = vertices.iter().map(|v| v.force).collect();
        let mut one_sided: Vec<Vector3<f64>> = vertices.iter().map(|v| v.one_sided_force).collect();
        let mut friction: Vec<Vector3<f64>> = vertices.iter().map(|v| v.friction).collect();
        let gravity_direction = lattice::complete(
            self.plan.dims,
            self.params.spacing,
            self.explorer.is_some(),
            load,
            lattice::VertexFields {
                known: &known,
                offsets: &offsets,
                forces: &mut forces,
                one_sided: &mut one_sided,
                friction: &mut friction,
            },
        );
        for (n, v) in vertices.iter_mut().enumerate() {
            v.force = forces[n];
            v.one_sided_force = one_sided[n];
            v.friction = friction[n];
            v.mass = v.force.dot(&gravity_direction) / self.params.g;
        }
        let extrapolated: Vec<Vertex> = self.plan.extrapolated.iter().map(|e| e.0).collect();
        let unreachable = vertices
            .iter()
            .filter(|v| !v.reached && !extrapolated.contains(&v.vertex))
            .map(|v| v.vertex)
            .collect();
        Some(CalibrationResult {
            gravity_direction,
            initial_mass: load.norm() / self.params.g,
            rest_point: self.rest_point,
            initial: self.initial,
            vertices,
            origin: self.plan.origin,
            dims: self.plan.dims,
            left_out: self.plan.left_out.clone(),
            unreachable,
            extrapolated,
            workspace: self.explorer.as_ref().map(|e| e.map().clone()),
            duration: self.end_time - self.start_time,
            time_spent: self.time_spent,
        })
    }

    /// The most calibration pushes beyond the forces it holds, N.
    fn push_limit(&self) -> f64 {
        PUSH_SHARE * self.params.max_force
    }

    /// First tick. X_C is where the handle rests (on hardware the user has brought it near the
    /// centre). A handle resting outside the grid's box (say on a stop below it) is first carried
    /// to the grid centre by gliding the field's centre there.
    fn start(&mut self, s: &DeviceState) -> ControlOutput {
        let t = s.time;
        self.start_time = t;
        self.rested_at = s.position;
        let (lo, hi) = self.params.workspace;
        let slack = ((hi - lo) / 2.0 * WORKSPACE_SLACK_SHARE).map(|d| d.max(WORKSPACE_SLACK_MIN));
        let outside = (lo - slack - s.position)
            .sup(&(s.position - hi - slack))
            .max();
        if outside > 0.0 {
            return self.fail(CalibrationFailure::OutsideWorkspace {
                position: s.position,
                lo,
                hi,
                outside,
            });
        }
        let (lo, hi) = (self.plan.origin, self.plan.far_corner());
        let inside = (0..3).all(|a| s.position[a] >= lo[a] && s.position[a] <= hi[a]);
        let to = if inside {
            s.position
        } else {
            self.params.centre
        };
        let cells = (to - s.position).norm() / self.params.spacing;
        let field = Glide {
            from: s.position,
            to,
            start: t,
            duration: if inside {
                0.0
            } else {
                self.params.move_time * cells.max(1.0)
            },
        };
        self.rest_point = to;
        self.phase = Phase::Catch(field);
        self.emit(CalibrationEvent::InitStarted);
        ControlOutput::force(Vector3::zeros())
    }

    /// The initial field centred on `centre`: k_init (X_C − X) − c V̂ plus its gravity term.
    fn field_force(&self, centre: &Vector3<f64>, s: &DeviceState) -> Vector3<f64> {
        (centre - s.position) * self.params.k_init
            - s.velocity * (self.params.init_damping * self.field_scale)
            + self.catch_force
    }

    /// The initial field has waited for rest since `since`: after a second without one, halve
    /// its damping (at most three times). Damping strong for a light handle (c T / m near 1)
    /// makes it chatter through the velocity filter's lag, and it never comes to rest.
    fn field_back_off(&mut self, s: &DeviceState, since: f64) -> bool {
        let weight = 1.0 / self.params.n_init as f64;
        self.speed_square += (s.velocity.norm_squared() - self.speed_square) * weight;
        if s.time - since > GAIN_BACKOFF_AFTER && self.field_scale > MIN_GAIN_SCALE {
            self.field_scale *= 0.5;
            self.detector.reset();
            self.field_since = s.time;
            return true;
        }
        false
    }

    /// The steady-state test of the initial field: n_init samples within ε_init, or within
    /// `STEADY_STEPS` encoder steps where the encoder is that coarse.
    fn init_detector(&self) -> SteadyState {
        let step = self.noise.step();
        let eps = if step.is_finite() {
            self.params.eps_init.max(STEADY_STEPS * step)
        } else {
            self.params.eps_init
        };
        SteadyState::new(self.params.n_init, eps)
    }

    /// A steady state of the initial field, unless the handle chatters about it (small and fast
    /// enough to average out of the windows, but not of the velocity): then the damping is
    /// halved and the wait goes on.
    fn field_steady(&mut self, s: &DeviceState) -> Option<Vector3<f64>> {
        let steady = self.detector.push(&s.position)?;
        // An encoder step larger than the velocity filter's noise bound reads as a burst of
        // speed: raise the bound to the step and look again.
        let step = self.noise.step();
        if self.raise_filter_bound(step) {
            self.speed_square = 0.0;
            self.detector = self.init_detector();
            return None;
        }
        let flicker = if step.is_finite() {
            step / FLICKER_TIME
        } else {
            0.0
        };
        let chatter = CHATTER_SPEED.max(flicker);
        if self.speed_square.sqrt() > chatter && self.field_scale > MIN_GAIN_SCALE {
            self.field_scale *= 0.5;
            self.detector.reset();
            self.field_since = s.time;
            return None;
        }
        Some(steady)
    }

    /// The velocity filter's noise bound raised to an encoder `step` larger than it (a step
    /// reads as a burst of speed otherwise): whether it was.
    fn raise_filter_bound(&mut self, step: f64) -> bool {
        if step <= self.filter_bound {
            return false;
        }
        let Ok(filter) = Foaw::new(
            self.params.foaw_variant,
            step,
            self.params.max_window,
            self.params.period,
        ) else {
            return false;
        };
        self.filter = filter;
        self.filter_bound = step;
        true
    }

    /// Initialisation, catch (§3.1): the elastic field k_init (X_C − X) plus damping (an
    /// undamped spring never lets a frictionless handle settle) until the handle is at rest.
    /// Unlike the paper, no sag is needed: the load is measured next by pushing. Samples count
    /// only once the glide is over.
    fn catch(&mut self, s: &DeviceState, field: Glide) -> ControlOutput {
        let t = s.time;
        if t - field.start > self.params.vertex_timeout + field.duration {
            return self.fail(CalibrationFailure::InitTimeout {
                timeout: self.params.vertex_timeout,
            });
        }
        let mut force = self.field_force(&field.at(t), s);
        // A handle that has not moved yet may be held, or not where the box says: push gently
        // until it follows.
        self.followed |= (s.position - self.rested_at).norm() > SEEN_MOVING;
        let carry_limit = CARRY_SHARE * self.params.max_force;
        if !self.followed {
            force = force.cap_magnitude(carry_limit);
        }
        if field.progress(t) < 1.0 {
            return ControlOutput::force(force);
        }
        self.noise.push(&s.position);
        let since = self.field_since.max(field.start + field.duration);
        self.field_back_off(s, since);
        if self.field_steady(s).is_some() {
            let off = field.to - s.position;
            if !self.followed && off.norm() > SEEN_MOVING {
                return self.held(t, off.iamax(), carry_limit);
            }
            self.initial.noise = self.noise.sigma();
            // A step adopted from the bands' slips (below) stands if the handle is caught again.
            self.initial.step = self.noise.step().max(self.initial.step);
            self.set_slip();
            if self.params.prior.is_some() {
                return self.initialised_from(self.field_force(&field.to, s), s);
            }
            self.phase = self.init_band_along(0, t);
        }
        ControlOutput::force(force)
    }

    /// The initialisation from an earlier calibration's ([`super::Prior`]), the handle caught
    /// at X_C by the force `caught`: the load is the prior's, moved to within the prior
    /// friction of `caught` (where the handle came to rest, the field held the load to within
    /// the friction); then the first vertex.
    fn initialised_from(&mut self, caught: Vector3<f64>, s: &DeviceState) -> ControlOutput {
        let Some(prior) = &self.params.prior else {
            return ControlOutput::force(caught);
        };
        // The saved model's force at X_C where it gives one (the record's load is a band's
        // middle, a few tens of millinewtons off on a linkage).
        let load = prior.expected_at(&self.rest_point).unwrap_or(prior.load);
        self.initial.load = Vector3::from_fn(|a, _| {
            load[a].clamp(caught[a] - prior.friction[a], caught[a] + prior.friction[a])
        });
        self.initial.friction = prior.friction;
        self.initial.inertia = prior.inertia;
        // The encoder's step the calibration saw (a handle caught at once shows none).
        self.initial.step = self.initial.step.max(prior.step);
        self.set_slip();
        self.raise_filter_bound(self.initial.step);
        self.initialised();
        self.report_initialisation();
        self.catch_force = self.initial.load;
        self.vertex = 0;
        self.start_move(self.rest_point, s.time);
        ControlOutput::force(caught)
    }

    /// Initialisation, load and friction: the stick band along each axis under the initial
    /// field. Its middle is the load at X_C, its half-width the friction. A handle that does
    /// not move under the ramp's whole push is held (by a hand, say): catch it again and
    /// measure again, until the initialisation's time is up.
    fn init_band(&mut self, s: &DeviceState, mut probe: BandProbe) -> ControlOutput {
        let t = s.time;
        let a = probe.index();
        let force = self.field_force(&self.rest_point, s) + axis(a) * probe.offset(t);
        match probe.observe(s, &self.smoothed, &force) {
            Step::Running => self.phase = Phase::InitBand(probe),
            // A handle that rested on one encoder reading, without noise, showed no step while
            // it was caught: the slip threshold assumed a fine encoder, and a reading that flips
            // by one step without a slip (a handle resting at a step's edge) passed for one.
            // The band's slips have moved the handle since: with the step they showed, measure
            // the bands again.
            Step::Done(_) if self.initial.step == 0.0 && self.moving.step() > 0.0 => {
                self.initial.step = self.moving.step();
                self.set_slip();
                self.phase = self.init_band_along(0, t);
            }
            Step::Done(band) => {
                self.initial.load[a] = band.middle();
                self.initial.friction[a] = band.half_width();
                self.phase = if a < 2 {
                    self.init_band_along(a + 1, t)
                } else {
                    self.time_moving_mass(t)
                };
            }
            Step::Blocked { .. } => return self.held(t, a, self.push_limit()),
        }
        ControlOutput::force(force)
    }

    /// A slip is a move beyond the noise and beyond an encoder step (a reading flickering
    /// between two steps is no move); a reading within half a step and two standard deviations
    /// of where the handle stuck has not moved yet.
    fn set_slip(&mut self) {
        self.slip = (MIN_SLIP + 3.0 * self.initial.noise).max(SLIP_STEPS * self.initial.step);
        self.still = 0.5 * self.initial.step + 2.0 * self.initial.noise;
    }

    /// The band along axis `a` at X_C, from `t`.
    fn init_band_along(&self, a: usize, t: f64) -> Phase {
        Phase::InitBand(BandProbe::new(
            a,
            axis(a),
            self.init_ramp(),
            self.slip,
            self.still,
            t,
        ))
    }

    /// With the load and friction measured: back to X_C with the load as the field's gravity
    /// term, then the pulses that time the moving mass, from `t`.
    fn time_moving_mass(&mut self, t: f64) -> Phase {
        self.catch_force = self.initial.load;
        self.detector = self.init_detector();
        Phase::Recentre {
            axis: 0,
            excess: self.pulse_excess(0),
            since: t,
        }
    }

    /// The ramp of a band measurement at X_C, where the band is not known yet: from the rate
    /// that moves a frictionless handle by a slip in `DETECT_TIME` against the initial field,
    /// growing at once.
    fn init_ramp(&self) -> Ramp {
        Ramp {
            rate: self.init_ramp_rate(),
            steady: INIT_RAMP_STEADY,
            growth: INIT_RAMP_GROWTH,
            limit: self.push_limit(),
        }
    }

    fn init_ramp_rate(&self) -> f64 {
        (self.params.k_init * self.slip / DETECT_TIME).max(INIT_RAMP_RATE)
    }

    /// The half-width a frictionless handle of moving mass `m` seems to have at X_C: the
    /// initial field's force over a slip, plus what the ramp adds while m accelerates over a
    /// slip (x = r t³ / 6m).
    fn apparent_band(&self, m: f64) -> f64 {
        let rate = self.init_ramp_rate();
        self.params.k_init * self.slip + rate.powf(2.0 / 3.0) * (6.0 * m * self.slip).cbrt()
    }

    /// The handle did not move under `push` N along `axis`: wait for it to be let go, catching
    /// it again, or give up once the initialisation's time is up.
    fn held(&mut self, t: f64, axis: usize, push: f64) -> ControlOutput {
        if t - self.start_time > self.params.vertex_timeout {
            return self.fail(CalibrationFailure::Held {
                axis: ['x', 'y', 'z'][axis],
                push_n: push,
            });
        }
        self.catch_force = Vector3::zeros();
        self.detector = self.init_detector();
        self.phase = Phase::Catch(Glide {
            from: self.rest_point,
            to: self.rest_point,
            start: t,
            duration: 0.0,
        });
        ControlOutput::force(Vector3::zeros())
    }

    /// The least push beyond the band that times the moving mass well: the friction, a tenth of
    /// the load (the load changes over the pulse wherever the apparent mass varies), or
    /// `PULSE_MIN_EXCESS`.
    fn pulse_excess(&self, a: usize) -> f64 {
        self.initial.friction[a]
            .max(PULSE_LOAD_SHARE * self.initial.load.norm())
            .max(PULSE_MIN_EXCESS)
    }

    /// Initialisation: the initial field, with the measured load as its gravity term, brings the
    /// handle back to X_C and lets it settle; then the next pulse, or the first vertex.
    fn recentre(&mut self, s: &DeviceState, a: usize, excess: f64, since: f64) -> ControlOutput {
        let t = s.time;
        if t - since > self.params.vertex_timeout {
            return self.fail(CalibrationFailure::InitTimeout {
                timeout: self.params.vertex_timeout,
            });
        }
        let force = self.field_force(&self.rest_point, s);
        self.noise.push(&s.position);
        self.field_back_off(s, since.max(self.field_since));
        let Some(steady) = self.field_steady(s) else {
            return ControlOutput::force(force);
        };
        self.initial.noise = self.initial.noise.min(self.noise.sigma());
        if a == 3 {
            self.initialised();
            self.phase = Phase::InitStrokes(Strokes::along_axes(Stroke::SURVEY, steady, t));
            return ControlOutput::force(force);
        }
        self.phase = Phase::Pulse(Pulse::new(
            a,
            excess,
            PULSE_DISTANCE,
            PULSE_TIMEOUT,
            &steady,
            t,
        ));
        ControlOutput::force(self.pulse_force(a, excess))
    }

    /// The load plus the friction plus `excess` along +axis `a`, and no spring.
    fn pulse_force(&self, a: usize, excess: f64) -> Vector3<f64> {
        self.initial.load + axis(a) * (self.initial.friction[a] + excess)
    }

    /// Initialisation, moving mass: the pulse along one axis, then back to X_C. A pulse that did
    /// not move the handle in time is repeated twice as strong, up to the push limit.
    fn pulse(&mut self, s: &DeviceState, mut pulse: Pulse) -> ControlOutput {
        let t = s.time;
        let a = pulse.axis;
        let (next_axis, excess) = match pulse.observe(s) {
            Step::Running => {
                self.phase = Phase::Pulse(pulse);
                return ControlOutput::force(self.pulse_force(a, pulse.excess));
            }
            Step::Done(mass) => {
                self.initial.inertia[a] = mass;
                (a + 1, self.pulse_excess((a + 1).min(2)))
            }
            Step::Blocked { .. } => {
                let excess = 2.0 * pulse.excess;
                if excess > self.push_limit() {
                    return self.held(t, a, self.initial.friction[a] + pulse.excess);
                }
                (a, excess)
            }
        };
        self.detector = self.init_detector();
        self.phase = Phase::Recentre {
            axis: next_axis,
            excess,
            since: t,
        };
        ControlOutput::force(self.field_force(&self.rest_point, s))
    }

    /// The hold's gains and the friction's kind along each axis from what the initialisation
    /// measured.
    fn initialised(&mut self) {
        let (inertia, friction, load) = (
            self.initial.inertia,
            self.initial.friction,
            self.initial.load,
        );
        self.gains = AxisGains::from_measurement(
            &self.params.gains,
            &inertia,
            &friction,
            FRICTION_OFFSET.max(FRICTION_OFFSET_STEPS * self.initial.step),
            MAX_OMEGA_PERIODS / self.params.period,
        );
        self.initial.stiffness = self.gains.stiffness;
        self.settle_time = SETTLE_RADIANS / self.gains.slowest_omega(&inertia);
        self.friction_kind = [0, 1, 2].map(|a| {
            let apparent = self.apparent_band(inertia[a]);
            if friction[a] > DOMINANT_BANDS * apparent + DOMINANT_FLOOR {
                Friction::Dominant
            } else if friction[a] > apparent {
                Friction::Slight
            } else {
                Friction::None
            }
        });
        self.share_friction_kind();
        self.learn_normals = false;
        self.estimate = load;
        self.last_good = load;
    }

    /// The initialisation is over (after the survey strokes): what it measured.
    fn report_initialisation(&mut self) {
        let InitialMeasurement {
            load,
            friction,
            inertia,
            ..
        } = self.initial;
        self.emit(CalibrationEvent::InitDone {
            gravity_direction: if load.norm() > 0.0 {
                load.normalize()
            } else {
                Vector3::z()
            },
            initial_mass: load.norm() / self.params.g,
            friction,
            inertia,
        });
    }

    /// One mechanism, one kind of friction: where it dominates along one axis, a hold at rest
    /// without velocity feedback along the others too (they share its joints).
    fn share_friction_kind(&mut self) {
        if self.friction_kind.contains(&Friction::Dominant) {
            for kind in &mut self.friction_kind {
                if *kind == Friction::Slight {
                    *kind = Friction::Dominant;
                }
            }
        }
    }

    /// Set off from `from` toward the current vertex, with a fresh vertex record.
    fn start_move(&mut self, from: Vector3<f64>, t: f64) {
        let to = self.plan.path[self.vertex].position;
        self.approach = from;
        // With a saved model, the hold starts from the force last measured plus the model's
        // change from there (where the previous hold was measured, or X_C) to the vertex.
        let measured_there =
            self.vertex == 0 || self.results[self.vertex - 1].is_some_and(|r| r.reached);
        if let Some(prior) = self.params.prior.as_ref().filter(|_| measured_there) {
            if let (Some(there), Some(here)) = (prior.expected_at(&to), prior.expected_at(&from)) {
                self.estimate += there - here;
            }
        }
        // An explored grid's path jumps where it skips extrapolated vertices: start from the
        // force of the closest vertex calibrated so far (Eq. 12), not of the last one.
        if self.explorer.is_some() {
            let closest = self
                .results
                .iter()
                .flatten()
                .filter(|r| r.reached)
                .min_by(|a, b| {
                    let d = |r: &VertexResult| (r.vertex.position - to).norm();
                    d(a).total_cmp(&d(b))
                });
            if let Some(r) = closest {
                self.estimate = r.force;
            }
        }
        let duration = self.glide(from, to, t).duration;
        let prediction = (self.params.predict_vertices
            && self.explorer.is_none()
            && self.params.prior.is_none()
            && self.friction_kind.contains(&Friction::Dominant)
            && self.initial.friction.max() >= STROKES_AT_ONCE)
            .then(|| self.predicted_force(&to))
            .flatten();
        // An explored workspace may end short of a vertex the map holds: move no faster than
        // the walk's moves (minimum-jerk peak speed 1.875 d / T), so a stop met on the way is
        // met slowly; along an edge the walk travelled, as fast as its returns. The extra time
        // does not count against the vertex's time limit.
        let walked = self
            .explorer
            .as_ref()
            .is_some_and(|e| e.map().walked(&from, &to));
        let slowed = match (&self.explorer, walked) {
            (Some(_), true) => duration.max(1.875 * (to - from).norm() / explore::RETURN_SPEED),
            (Some(_), false) => duration.max(1.875 * (to - from).norm() / explore::PROBE_SPEED),
            (None, _) => duration,
        };
        self.phase = Phase::Move {
            path: Glide {
                from,
                to,
                start: t,
                duration: slowed,
            },
            walked,
            then: [None; 2],
        };
        self.vertex_start = t + (slowed - duration);
        self.vertex_began = t;
        self.fresh_attempt();
        if let Some(force) = prediction {
            self.estimate = force;
            self.strokes_at_once = true;
        }
        self.emit(CalibrationEvent::VertexStarted {
            vertex: self.vertex,
            of: self.plan.path.len(),
            at: self.plan.path[self.vertex],
            elapsed: self.elapsed(),
        });
    }

    /// A vertex's count of updates, rounds and rests starts afresh (a new vertex, or the second
    /// attempt at one).
    fn fresh_attempt(&mut self) {
        self.iteration = 0;
        self.rounds = 0;
        self.previous_offset = None;
        self.near_rests = 0;
        self.one_sided = None;
        self.band_friction = Vector3::zeros();
        // With a saved model every hold under friction starts from its force (`start_move`).
        self.strokes_at_once = self.params.prior.is_some() && self.next_band_axis(None).is_some();
        self.detector = self.vertex_detector();
    }

    /// The holding force at `to` predicted from the vertices measured so far: by the arm's
    /// gravity fitted to them where the profile gives an arm and the fit explains them
    /// ([`ArmPrediction`]: 0.1–10 mN off on the simulated linkages, once three are measured),
    /// else by three of them that make a parallelogram with it ([`Self::force_from_neighbours`]:
    /// 10–50 mN off on the PHANToM, up to 0.4 N on the delta).
    fn predicted_force(&self, to: &Vector3<f64>) -> Option<Vector3<f64>> {
        self.arm_fit
            .as_ref()
            .and_then(|fit| fit.predict(to))
            .or_else(|| self.force_from_neighbours(to))
    }

    /// The holding force at `to` predicted from three vertices measured so far that make a
    /// parallelogram with it, to = a + b − c (a = b: a straight line through c and a): F(a) +
    /// F(b) − F(c), exact for a field linear over the stencil; the most compact such stencil.
    /// None while no three do. A stencil within [`PREDICT_REACH`] has every vertex within two
    /// spacings of `to` along each axis: those are set out on a 5 × 5 × 5 table of offsets
    /// first, so the search costs the same on any grid (no allocation: it runs on the servo
    /// thread).
    fn force_from_neighbours(&self, to: &Vector3<f64>) -> Option<Vector3<f64>> {
        const SIDE: i32 = 5;
        let spacing = self.params.spacing;
        // The offset of `x` from `to` in whole spacings, -2..=2 along each axis, if it is one.
        let cell = |x: &Vector3<f64>| -> Option<[i32; 3]> {
            let steps = (x - to) / spacing;
            let rounded = steps.map(f64::round);
            let inside = rounded.iter().all(|k| k.abs() <= 2.0);
            ((steps - rounded).norm() < PREDICT_MATCH && inside)
                .then(|| [0, 1, 2].map(|a| rounded[a] as i32))
        };
        let slot =
            |o: [i32; 3]| ((o[0] + 2) * SIDE * SIDE + (o[1] + 2) * SIDE + (o[2] + 2)) as usize;
        let mut table = [None; (SIDE * SIDE * SIDE) as usize];
        let mut near = [[0; 3]; (SIDE * SIDE * SIDE) as usize];
        let mut count = 0;
        for r in self.results.iter().flatten().filter(|r| r.reached) {
            if let Some(o) = cell(&r.vertex.position) {
                if table[slot(o)].is_none() {
                    near[count] = o;
                    count += 1;
                }
                table[slot(o)] = Some(r.force);
            }
        }
        let near = &near[..count];
        let length = |o: [i32; 3]| f64::from(o[0] * o[0] + o[1] * o[1] + o[2] * o[2]).sqrt();
        let mut best: Option<(f64, Vector3<f64>)> = None;
        for &a in near {
            for &c in near {
                // to = a + b − c, with `to` at the origin of the offsets: b = c − a.
                let b = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
                if a == c || b.iter().any(|k| k.abs() > 2) {
                    continue;
                }
                let (Some(force_a), Some(force_b), Some(force_c)) =
                    (table[slot(a)], table[slot(b)], table[slot(c)])
                else {
                    continue;
                };
                let spread = length(a) + length(b) + length(c);
                if spread <= PREDICT_REACH && best.is_none_or(|(s, _)| spread < s) {
                    best = Some((spread, force_a + force_b - force_c));
                }
            }
        }
        best.map(|(_, force)| force)
    }

    /// The steady-state test at vertices: n_M samples within ε_M, window means agreeing within
    /// what the position noise allows (at most ε_M/10): the closer a hold is to rest, the
    /// closer the force it applies is to the load.
    fn vertex_detector(&self) -> SteadyState {
        let n = self.params.n_m;
        let eps = self.params.eps_m;
        let creep = (CREEP_SIGMAS * self.initial.noise * (2.0 / n as f64).sqrt())
            .max(MIN_CREEP)
            .min(eps / 10.0);
        SteadyState::with_creep(n, eps, creep)
    }

    /// The hold toward `target`: the PD (backed off by `gain_scale`) plus the gravity term
    /// `feedforward` (Eq. 10 with the force estimate as a vector).
    fn hold_force(
        &self,
        target: &Vector3<f64>,
        s: &DeviceState,
        feedforward: &Vector3<f64>,
    ) -> Vector3<f64> {
        self.gains
            .scaled(self.gain_scale)
            .pd_force(target, s, feedforward)
    }

    /// The hold at rest: like [`Self::hold_force`], without velocity feedback along axes whose
    /// friction dissipates more than the feedback would (its noise would shake a stuck handle),
    /// and pulling on the smoothed position there, while the handle is at rest; once it moves
    /// faster than `RINGING_SPEED`, the full hold, so that it cannot ring up.
    fn still_force(
        &self,
        target: &Vector3<f64>,
        s: &DeviceState,
        feedforward: &Vector3<f64>,
    ) -> Vector3<f64> {
        let mut gains = self.gains.scaled(self.gain_scale);
        let mut still = *s;
        let at_rest = s.velocity.norm() < RINGING_SPEED;
        for a in 0..3 {
            if self.friction_kind[a] == Friction::Dominant && at_rest {
                gains.damping[a] = 0.0;
                still.position[a] = self.smoothed[a];
            }
        }
        gains.pd_force(target, &still, feedforward)
    }

    /// Move (§3.2): the PD (with the force estimate so far) follows the glide to the vertex,
    /// then holds it.
    fn move_to_vertex(
        &mut self,
        s: &DeviceState,
        path: Glide,
        walked: bool,
        then: [Option<Vector3<f64>>; 2],
    ) -> ControlOutput {
        // In an explored workspace, a handle that stops following the move has met a stop the
        // map did not know: the vertex is out of reach, and the hold stays where the handle is.
        // Along an edge the walk travelled nothing is in the way, and the faster move lags more.
        if self.explorer.is_some()
            && !walked
            && (path.at(s.time) - s.position).norm() > explore::CONTACT_LAG
        {
            return self.skip(s, (path.to - s.position).norm(), None);
        }
        if path.progress(s.time) >= 1.0 {
            match then {
                [Some(next), after] => {
                    self.phase = Phase::Move {
                        path: self.glide(path.to, next, s.time),
                        walked,
                        then: [after, None],
                    };
                }
                // F̂ predicted under friction: the strokes measure at once (and again if they
                // moved F̂ far), with no rests or bands first.
                _ if self.strokes_at_once => {
                    let vertex = self.plan.path[self.vertex];
                    let error = (vertex.position - s.position).norm();
                    return self.stroke(s, vertex, StrokeRun::first(error, None));
                }
                _ => self.settle_from(s.time),
            }
        }
        ControlOutput::force(self.hold_force(&path.at(s.time), s, &self.estimate))
    }

    /// Settle from time `t`: a fresh steady-state test after the settle time.
    fn settle_from(&mut self, t: f64) {
        self.detector.reset();
        self.phase = Phase::Settle { since: t };
    }

    /// `vertex_timeout` has passed at the current vertex. With friction, a hold may keep coming
    /// to rest off the vertex, creep, or its bands may not agree in time: strokes through the
    /// vertex measure its force wherever the hold left the handle, and the vertex fails only if
    /// something stops them. Without friction it fails at once.
    fn out_of_time(&mut self, s: &DeviceState, failure: CalibrationFailure) -> ControlOutput {
        if self
            .friction_kind
            .iter()
            .all(|&kind| kind == Friction::None)
        {
            let distance = (self.plan.path[self.vertex].position - s.position).norm();
            return self.give_up(s, distance, Some(failure));
        }
        let vertex = self.plan.path[self.vertex];
        let error = (vertex.position - self.smoothed).norm();
        // Updates that did not converge may have taken F̂ far off, and a hold that far off the
        // load leaves the handle outside the strokes' windows: start from the last vertex's.
        self.estimate = self.last_good;
        self.gain_scale = 1.0;
        self.stroke(s, vertex, StrokeRun::first(error, Some(failure)))
    }

    fn vertex_timed_out(&self, t: f64) -> Option<CalibrationFailure> {
        (t - self.vertex_start > self.params.vertex_timeout).then_some(
            CalibrationFailure::VertexTimeout {
                vertex: self.plan.path[self.vertex],
                timeout: self.params.vertex_timeout,
                iterations: self.iteration,
            },
        )
    }

    /// Hold (§3.2): the PD holds the vertex with the force estimate (Eq. 10). Each steady state
    /// after the settle time is a rest to act on; a hold without a steady state backs off its
    /// gains.
    fn settle(&mut self, s: &DeviceState, since: f64) -> ControlOutput {
        let t = s.time;
        let vertex = self.plan.path[self.vertex];
        if let Some(failure) = self.vertex_timed_out(t) {
            return self.out_of_time(s, failure);
        }
        let force = self.hold_force(&vertex.position, s, &self.estimate);
        if t - since < self.settle_time / self.gain_scale.sqrt() {
            return ControlOutput::force(force);
        }
        match self.detector.push(&s.position) {
            Some(rest) => self.at_rest(s, vertex, rest, force),
            None => {
                if t - since > self.settle_time + GAIN_BACKOFF_AFTER
                    && self.gain_scale > MIN_GAIN_SCALE
                {
                    self.back_off(t);
                }
                ControlOutput::force(force)
            }
        }
    }

    /// Halve the PD's gains (not the force estimate): gains built on a mass several times too
    /// large make the hold oscillate through the velocity filter's lag, and no steady state
    /// comes. The next update restores them.
    fn back_off(&mut self, t: f64) {
        self.gain_scale *= 0.5;
        self.settle_from(t);
        self.emit(CalibrationEvent::GainsReduced {
            vertex: self.vertex,
            scale: self.gain_scale,
        });
    }

    /// How far from the vertex along axis `a` a rest still counts as reached, m: the friction
    /// band's span of offset a few times over, plus the noise.
    fn reach_tolerance(&self, a: usize) -> f64 {
        let stiffness = self.gains.stiffness[a] * self.gain_scale;
        REACH_BANDS * self.initial.friction[a] / stiffness + 3.0 * self.initial.noise + REACH_MARGIN
    }

    /// A rest X̄ at `vertex` X_i. There the hold applies F̂ + K (X_i − X̄), which balances the
    /// load up to the friction. Near the vertex: measure the stick band. Off it: that force
    /// becomes F̂ (the vector form of the signed Eq. 11; the paper's norm loses the sign), and
    /// the hold pulls the handle closer; if the previous update did not bring it closer, push.
    fn at_rest(
        &mut self,
        s: &DeviceState,
        vertex: Vertex,
        rest: Vector3<f64>,
        force: Vector3<f64>,
    ) -> ControlOutput {
        let t = s.time;
        let offset = vertex.position - rest;
        let applied =
            self.estimate + offset.component_mul(&self.gains.scaled(self.gain_scale).stiffness);
        if (0..3).all(|a| offset[a].abs() <= self.reach_tolerance(a)) {
            // The hold now centres on the rest itself: no jump, since F̂ becomes the force it
            // applies there (inside the stick band: the handle rests under it).
            self.one_sided.get_or_insert(applied);
            self.estimate = applied;
            self.rest = rest;
            self.near_rests += 1;
            self.earlier_rounds = (Vector3::zeros(), Vector3::zeros(), 0);
            return self.start_round(s);
        }
        let distance = offset.norm();
        if self
            .previous_offset
            .is_some_and(|previous| distance > PROGRESS * previous)
        {
            let rate = (0..3)
                .map(|a| self.band_ramp(&axis(a)).rate)
                .fold(0.0, f64::max);
            let ramp = Ramp {
                rate,
                steady: 0.0,
                growth: RAMP_GROWTH,
                limit: self.push_limit(),
            };
            self.previous_offset = None;
            self.phase = Phase::Push(Push::new(offset / distance, ramp, self.slip, t));
            return ControlOutput::force(force);
        }
        self.previous_offset = Some(distance);
        self.update(s, applied, distance)
    }

    /// F̂ ← `force`; count it, and give up after `max_iterations`.
    fn update(&mut self, s: &DeviceState, force: Vector3<f64>, error: f64) -> ControlOutput {
        self.estimate = force;
        self.gain_scale = 1.0;
        self.iteration += 1;
        self.emit(CalibrationEvent::Iteration {
            vertex: self.vertex,
            iteration: self.iteration,
            force,
            error,
        });
        if self.iteration >= self.params.max_iterations {
            let vertex = self.plan.path[self.vertex];
            let failure = CalibrationFailure::TooManyIterations {
                vertex,
                iterations: self.iteration,
            };
            return self.give_up(s, (vertex.position - s.position).norm(), Some(failure));
        }
        self.settle_from(s.time);
        let vertex = self.plan.path[self.vertex].position;
        ControlOutput::force(self.hold_force(&vertex, s, &self.estimate))
    }

    /// The ramp of a band measurement along the unit `direction` at a vertex: steady at the
    /// rate that crosses the friction band measured at X_C in `CROSSING_TIME` or moves a
    /// frictionless handle by a slip in `DETECT_TIME`, whichever is faster, over twice the band
    /// (and the slip's force), growing beyond. Off the axes, the axes' stiffness and band are
    /// weighted by the direction's squared components.
    fn band_ramp(&self, direction: &Vector3<f64>) -> Ramp {
        let weights = direction.component_mul(direction);
        let stiffness = weights.dot(&self.gains.stiffness) * self.gain_scale;
        let slip_force = stiffness * self.slip;
        let width = 2.0 * weights.dot(&self.initial.friction);
        let rate = (slip_force / DETECT_TIME).max(width / CROSSING_TIME);
        Ramp {
            rate,
            steady: 2.0 * (width + 4.0 * slip_force),
            growth: RAMP_GROWTH,
            limit: self.push_limit(),
        }
    }

    /// Band `k` of a round, starting at time `t`: along the axis k while the normals are the
    /// axes, else along the direction that changes the force on the k-th pair of faces only
    /// (the dual basis of the normals: for joint friction, the force that loads one joint),
    /// so that its chord leaves the stick region through those two faces wherever it starts.
    fn band_probe(&self, k: usize, t: f64) -> BandProbe {
        let rows = Matrix3::from_rows(&self.normals.map(|n| n.transpose()));
        let direction = rows
            .try_inverse()
            .and_then(|dual| dual.column(k).try_normalize(1e-12))
            .unwrap_or_else(|| axis(k));
        BandProbe::new(
            k,
            direction,
            self.band_ramp(&direction),
            self.slip,
            self.still,
            t,
        )
    }

    /// The first axis after `a` (all of them: from `None`) with friction, if any.
    fn next_band_axis(&self, after: Option<usize>) -> Option<usize> {
        let from = after.map_or(0, |a| a + 1);
        (from..3).find(|&a| self.friction_kind[a] != Friction::None)
    }

    /// A round of band measurements along the axes with friction: x, y, then z.
    fn start_round(&mut self, s: &DeviceState) -> ControlOutput {
        let t = s.time;
        let Some(a) = self.next_band_axis(None) else {
            // No friction anywhere: the force applied at this rest is the load. It is taken at
            // the second rest near the vertex, which follows a correction too small to leave a
            // transient (the paper's "n_M samples within ε_M", read as twice in a row).
            let vertex = self.plan.path[self.vertex];
            let error = (vertex.position - self.rest).norm();
            if self.near_rests < 2 {
                return self.update(s, self.estimate, error);
            }
            self.measured_at = self.rest;
            return self.vertex_done(s, vertex, error);
        };
        self.phase = Phase::Band {
            probe: self.band_probe(a, t),
            round_start: self.estimate,
            anchor: self.smoothed,
        };
        ControlOutput::force(self.still_force(&self.smoothed, s, &self.estimate))
    }

    /// The stick band at the vertex, axis by axis: F̂ along the axis becomes the band's middle.
    /// After z, the round is over: the vertex is done once a round changes F̂ by less than a
    /// quarter of the band (or after `MAX_ROUNDS`); otherwise the handle settles again (it may
    /// have moved under the new force) and another round follows. A direction the handle does
    /// not move along under the whole push is blocked: the vertex is unreachable.
    fn band(
        &mut self,
        s: &DeviceState,
        mut probe: BandProbe,
        round_start: Vector3<f64>,
        anchor: Vector3<f64>,
    ) -> ControlOutput {
        let t = s.time;
        let vertex = self.plan.path[self.vertex];
        if let Some(failure) = self.vertex_timed_out(t) {
            return self.out_of_time(s, failure);
        }
        let feedforward = self.estimate + probe.direction() * probe.offset(t);
        let force = self.still_force(&anchor, s, &feedforward);
        match probe.observe(s, &self.smoothed, &force) {
            Step::Running => {
                self.phase = Phase::Band {
                    probe,
                    round_start,
                    anchor,
                };
                ControlOutput::force(force)
            }
            Step::Blocked { .. } => self.give_up(s, (vertex.position - self.rest).norm(), None),
            Step::Done(band) => {
                let k = probe.index();
                // F̂ moves along the band's direction until its load on the band's pair of faces
                // is the band's middle; the direction loads no other pair.
                let (n, d) = (self.normals[k], band.direction);
                self.estimate += d * (n.dot(&(band.midpoint() - self.estimate)) / n.dot(&d));
                self.faces[k] = band.half_width() * n.dot(&d);
                self.strict[k] = band.constraint();
                let loose = band.loose_constraint();
                // Joint friction: from the end of this round on, learn its normals.
                self.joint_friction |=
                    loose.0.dot(&d) < ALONG_PUSH && !self.friction_kind.contains(&Friction::None);
                // Along the axes a ball's chord crossed off its centre still gives a constraint.
                self.constraints[k] = if self.learn_normals {
                    self.strict[k]
                } else {
                    Some(loose)
                };
                self.slips[k] = band.slips();
                self.band_at[k] = band.at;
                if let Some(next) = self.next_band_axis(Some(k)) {
                    self.phase = Phase::Band {
                        probe: self.band_probe(next, t),
                        round_start,
                        anchor: self.smoothed,
                    };
                    return ControlOutput::force(force);
                }
                self.round_done(s, vertex, round_start, force)
            }
        }
    }

    /// A round is over: the vertex is done once a round changed F̂ by little (the chords the
    /// bands were measured along then pass through the band's middle), or after `MAX_ROUNDS`;
    /// otherwise another round follows at once, or, if the handle has crept off the vertex,
    /// after it settles again.
    fn round_done(
        &mut self,
        s: &DeviceState,
        vertex: Vertex,
        round_start: Vector3<f64>,
        force: Vector3<f64>,
    ) -> ControlOutput {
        self.rounds += 1;
        self.iteration += 1;
        let consistent = self.solve_constraints();
        if self.joint_friction && !self.learn_normals {
            // The round that showed joint friction brought F̂ nearer the centre along the
            // axes; the vertex is measured afresh along the normals its slips teach.
            self.learn_normals = true;
            self.rounds = 0;
            self.earlier_rounds = (Vector3::zeros(), Vector3::zeros(), 0);
            self.learn_normals();
            return self.start_round(s);
        }
        if self.learn_normals {
            self.learn_normals();
        }
        self.band_friction = self.axis_friction();
        let change = self.estimate - round_start;
        // While the normals are still being learnt, a round whose chords did not all cross one
        // pair of faces is no measurement of the same thing as the next one.
        let measured = consistent || !self.learn_normals;
        let settled = measured
            && (0..3).all(|k| {
                self.friction_kind[k] == Friction::None
                    || self.normals[k].dot(&change).abs()
                        <= ROUND_SHARE * self.faces[k] + FORCE_TOLERANCE
            });
        let error = (vertex.position - self.rest).norm();
        self.emit(CalibrationEvent::Iteration {
            vertex: self.vertex,
            iteration: self.iteration,
            force: self.estimate,
            error,
        });
        // A vertex whose last round was no clean measurement gets one more while it has time.
        let more = self.rounds < MAX_ROUNDS
            || (!measured
                && self.rounds < MAX_ROUNDS + 1
                && s.time - self.vertex_start < 0.5 * self.params.vertex_timeout);
        if (settled && self.rounds >= MIN_ROUNDS) || !more {
            // The rounds measured the same band independently: their mean shrinks what the
            // slips' timing and the position noise scatter.
            // A last round that was no such measurement is left out if there are others.
            let (sum, at, count) = self.earlier_rounds;
            let here = self.round_at();
            (self.estimate, self.measured_at) = if measured || count == 0 {
                let n = f64::from(count + 1);
                ((sum + self.estimate) / n, (at + here) / n)
            } else {
                (sum / f64::from(count), at / f64::from(count))
            };
            if !self.friction_kind.contains(&Friction::Slight) {
                return self.stroke(s, vertex, StrokeRun::first(error, None));
            }
            self.detector.reset();
            self.phase = Phase::Check {
                anchor: self.smoothed,
                since: s.time,
            };
            return ControlOutput::force(force);
        }
        if self.iteration >= self.params.max_iterations {
            let failure = CalibrationFailure::TooManyIterations {
                vertex,
                iterations: self.iteration,
            };
            return self.give_up(s, (vertex.position - s.position).norm(), Some(failure));
        }
        // The slips of a round move the handle a little; a new estimate may move it a little
        // more: measure again where it is unless it has gone far.
        let offset = vertex.position - self.smoothed;
        if (0..3).all(|a| offset[a].abs() <= ROUND_REACH * self.reach_tolerance(a)) {
            if measured {
                self.earlier_rounds.0 += self.estimate;
                self.earlier_rounds.1 += self.round_at();
                self.earlier_rounds.2 += 1;
            }
            return self.start_round(s);
        }
        self.settle_from(s.time);
        ControlOutput::force(force)
    }

    /// Where this round's bands were measured, on average, m.
    fn round_at(&self) -> Vector3<f64> {
        let bands = (0..3).filter(|&a| self.friction_kind[a] != Friction::None);
        let (sum, count) = bands.fold((Vector3::zeros(), 0.0), |(sum, n), a| {
            (sum + self.band_at[a], n + 1.0)
        });
        if count > 0.0 {
            sum / count
        } else {
            self.rest
        }
    }

    /// The check (see [`Phase::Check`]): along each axis the handle moved on by more than a
    /// slip, the force it rests under replaces the band's middle.
    fn check(&mut self, s: &DeviceState, anchor: Vector3<f64>, since: f64) -> ControlOutput {
        let t = s.time;
        if let Some(failure) = self.vertex_timed_out(t) {
            return self.out_of_time(s, failure);
        }
        let force = self.hold_force(&anchor, s, &self.estimate);
        if t - since < self.settle_time {
            return ControlOutput::force(force);
        }
        let Some(rest) = self.detector.push(&s.position) else {
            return ControlOutput::force(force);
        };
        let stiffness = self.gains.scaled(self.gain_scale).stiffness;
        // Beyond the noise of the anchor (a mean of 8 samples) and of the rest (of n_M), or half
        // an encoder step, whichever is more.
        let moved = (3.0 * self.initial.noise * (0.125 + 1.0 / self.params.n_m as f64).sqrt())
            .max(0.5 * self.initial.step);
        for a in 0..3 {
            if self.friction_kind[a] == Friction::Slight && (rest[a] - anchor[a]).abs() > moved {
                self.estimate[a] += stiffness[a] * (anchor[a] - rest[a]);
            }
        }
        let vertex = self.plan.path[self.vertex];
        self.stroke(
            s,
            vertex,
            StrokeRun::first((vertex.position - rest).norm(), None),
        )
    }

    /// With friction at the vertex, the bands have brought F̂ within a few millinewtons; strokes
    /// through the vertex measure it to one ([`Strokes`]), following [`Phase::Strokes`].
    fn stroke(&mut self, s: &DeviceState, vertex: Vertex, run: StrokeRun) -> ControlOutput {
        let strokes = self
            .params
            .arm
            .and_then(|arm| {
                Strokes::along_the_arm(Stroke::MEASURE_ALONG_THE_ARM, &arm, vertex.position, s.time)
            })
            .unwrap_or_else(|| {
                Strokes::through_every_joint(Stroke::MEASURE, vertex.position, s.time)
            });
        self.phase = Phase::Strokes { strokes, run };
        ControlOutput::force(self.hold_force(&vertex.position, s, &self.estimate))
    }

    /// The hold on a stroke's set point at full gains (a backed-off hold would trail it further),
    /// damping the velocity relative to the set point's; along axes where friction dominates,
    /// only `STROKE_DAMPING` of it.
    fn stroke_force(&self, strokes: &Strokes, s: &DeviceState) -> Vector3<f64> {
        let (target, velocity) = strokes.set_point(s.time);
        let mut relative = *s;
        relative.velocity -= velocity;
        let mut gains = self.gains;
        for a in 0..3 {
            if self.friction_kind[a] == Friction::Dominant {
                gains.damping[a] *= STROKE_DAMPING;
            }
        }
        gains.pd_force(&target, &relative, &self.estimate)
    }

    /// The force of the hold's spring, at full gains, on the handle (its smoothed position) off
    /// `target`, N.
    fn spring(&self, target: &Vector3<f64>) -> Vector3<f64> {
        self.gains
            .stiffness
            .component_mul(&(target - self.smoothed))
    }

    /// [`Self::spring`] when it keeps the handle off `target` with more than strokes tolerate in
    /// their feedforward (`STROKE_REPEAT`), but no more than the push limit: friction yields to
    /// that much, so a handle held off by more is on something else (a stop), or F̂ is far off,
    /// and the force there says nothing about the load. It is read as the strokes' home leg
    /// ends, without waiting for the handle to come to rest (requiring rest there skipped the
    /// retry the delta at 0.02 N at the handle needs).
    fn held_off(&self, target: &Vector3<f64>) -> Option<Vector3<f64>> {
        let spring = self.spring(target);
        (STROKE_REPEAT..=self.push_limit())
            .contains(&spring.norm())
            .then_some(spring)
    }

    /// Whether the bands at X_C misread some frictional axis (one whose survey strokes slid
    /// against more than `STROKE_FRICTION`, which a frictionless handle's passes stay under):
    /// its friction under `MISREAD_SHARE` of the strokes', or its middle further from the
    /// strokes' force than `STROKE_REPEAT` (PHANToM unit 2, seed 1, 0.02 N: 47 mN off along y,
    /// and a 925 g moving mass timed from it).
    fn bands_misread(&self, stroked: &Stroked) -> bool {
        (0..3).any(|a| {
            let sliding = stroked.friction[a].abs();
            let narrow = self.initial.friction[a] < MISREAD_SHARE * sliding;
            let off = (stroked.force[a] - self.initial.load[a]).abs() > STROKE_REPEAT;
            sliding > STROKE_FRICTION && (narrow || off)
        })
    }

    /// The strokes at X_C ([`Phase::InitStrokes`]): an axis the bands took for frictionless
    /// whose passes differ by more than `STROKE_FRICTION` has friction after all (or viscous
    /// damping well beyond 1 N·s/m, which strokes measure through as well), and is measured as
    /// such at every vertex. Then the first vertex.
    fn init_strokes(&mut self, s: &DeviceState, mut strokes: Strokes) -> ControlOutput {
        let force = self.stroke_force(&strokes, s);
        match strokes.observe(s, &force) {
            Step::Running => {
                self.phase = Phase::InitStrokes(strokes);
                return ControlOutput::force(force);
            }
            // A band far narrower than the friction the strokes slide against was misread (the
            // handle shook at the start of a crossing, and a slip was taken early), and so was
            // its middle. The moving mass was timed with that load and friction, and the gains
            // built on both: time it again with the strokes' load and sliding friction, then
            // survey again.
            Step::Done(stroked)
                if self.init_remeasured < INIT_REMEASURES && self.bands_misread(&stroked) =>
            {
                self.init_remeasured += 1;
                self.initial.load = stroked.force;
                self.initial.friction = stroked.friction.abs();
                self.phase = self.time_moving_mass(s.time);
                return ControlOutput::force(self.field_force(&self.rest_point, s));
            }
            Step::Done(stroked) => {
                for a in 0..3 {
                    if self.friction_kind[a] == Friction::None
                        && stroked.friction[a].abs() > STROKE_FRICTION
                    {
                        self.friction_kind[a] = Friction::Slight;
                    }
                }
                self.share_friction_kind();
            }
            // The hold did not carry the handle through a window: the bands misread its load
            // so far that the hold keeps it off the window (a stop within 2 mm of the user's
            // centre is unlikely). Measure the bands again.
            Step::Blocked { .. } if self.init_remeasured < INIT_REMEASURES => {
                self.init_remeasured += 1;
                self.phase = self.init_band_along(0, s.time);
                return ControlOutput::force(self.field_force(&self.rest_point, s));
            }
            // A stop within a stroke of X_C: the bands' classes stand.
            Step::Blocked { .. } => {}
        }
        self.report_initialisation();
        if let Some(explorer) = &mut self.explorer {
            explorer.begin(strokes.centre(), s.time);
            self.phase = Phase::Explore;
            return ControlOutput::force(self.stroke_force(&strokes, s));
        }
        self.vertex = 0;
        self.start_move(strokes.centre(), s.time);
        ControlOutput::force(force)
    }

    fn strokes(&mut self, s: &DeviceState, mut strokes: Strokes, run: StrokeRun) -> ControlOutput {
        let force = self.stroke_force(&strokes, s);
        let vertex = self.plan.path[self.vertex];
        match strokes.observe(s, &force) {
            Step::Running => {
                self.phase = Phase::Strokes { strokes, run };
                ControlOutput::force(force)
            }
            Step::Done(stroked) => {
                let change = (stroked.force - self.estimate).norm();
                self.estimate = stroked.force;
                self.measured_at = strokes.centre();
                self.iteration += 1;
                let again =
                    STROKE_REPEAT.max(self.params.strokes_again_share * stroked.force.norm());
                if change > again && run.repeat {
                    // A hold that far off the load kept the handle off the middle of the
                    // windows: measure again from what the strokes found.
                    let again = StrokeRun {
                        repeat: false,
                        bands_force: None,
                        ..run
                    };
                    return self.stroke(s, vertex, again);
                }
                self.emit(CalibrationEvent::Iteration {
                    vertex: self.vertex,
                    iteration: self.iteration,
                    force: self.estimate,
                    error: run.error,
                });
                self.vertex_done(s, vertex, run.error)
            }
            // Held off by more than friction yields to: F̂ is no measurement of the load (the
            // delta at 0.02 N, unit 1, seed 3: rounds of bands that disagreed left it 2.8 N
            // off, 264 % of the holding force) or a stop is within a stroke of the vertex.
            // Either way the vertex is measured again from beside it.
            Step::Blocked { .. } if self.spring(&vertex.position).norm() > self.push_limit() => {
                let off = (vertex.position - self.smoothed).norm();
                let failure = CalibrationFailure::HeldOff {
                    vertex,
                    offset_mm: off * 1e3,
                };
                self.give_up(s, off, Some(failure))
            }
            // The hold kept the handle off the windows: where it rests now, the force that holds
            // it there is the holding force to within the friction, whatever F̂ was. An F̂ that
            // far off (rounds whose bands misread a ball of friction at the handle as a joint's
            // faces) is replaced by that force and the strokes run once more, keeping the bands'
            // F̂; a stop stays a stop, and blocks them again.
            Step::Blocked { .. } if run.repeat && run.bands_force.is_none() => {
                match self.held_off(&vertex.position) {
                    Some(spring) => {
                        let retry = StrokeRun {
                            bands_force: Some(self.estimate),
                            ..run
                        };
                        self.estimate += spring;
                        self.stroke(s, vertex, retry)
                    }
                    None => self.blocked(s, vertex, run),
                }
            }
            Step::Blocked { .. } => self.blocked(s, vertex, run),
        }
    }

    /// Something within a stroke's reach of the vertex stops the handle: the bands'
    /// measurement stands, if they finished.
    fn blocked(&mut self, s: &DeviceState, vertex: Vertex, run: StrokeRun) -> ControlOutput {
        if let Some(bands_force) = run.bands_force {
            self.estimate = bands_force;
        }
        match run.late {
            Some(failure) => {
                let distance = (vertex.position - s.position).norm();
                self.give_up(s, distance, Some(failure))
            }
            None => self.vertex_done(s, vertex, run.error),
        }
    }

    /// F̂ from the round's bands: the force c with n·c = b for each band's constraint
    /// ([`Band::constraint`]) and, along axes without friction, c = F̂ there. A band without a
    /// constraint (its chord left through the faces of two joints), or whose constraint repeats
    /// an earlier band's pair of faces, keeps its pair's normal n and the middle its update put
    /// into F̂ (n·c = n·F̂). Where every axis has friction, the constraints' normals become the
    /// normals the next round's directions follow. Normals too close to coplanar change
    /// nothing. True when every band gave a constraint of its own.
    fn solve_constraints(&mut self) -> bool {
        let mut rows = [(Vector3::zeros(), 0.0); 3];
        let mut consistent = true;
        for k in 0..3 {
            if self.friction_kind[k] == Friction::None {
                rows[k] = (axis(k), self.estimate[k]);
                continue;
            }
            let own = self.constraints[k].filter(|(n, _)| {
                rows[..k]
                    .iter()
                    .all(|(other, _)| n.dot(other).abs() < SAME_FACES)
            });
            consistent &= own.is_some();
            let n = self.normals[k];
            rows[k] = own.unwrap_or((n, n.dot(&self.estimate)));
        }
        let n = Matrix3::from_rows(&rows.map(|(n, _)| n.transpose()));
        if n.determinant().abs() < MIN_CONSTRAINT_VOLUME {
            return false;
        }
        let Some(c) = n.lu().solve(&Vector3::from(rows.map(|(_, b)| b))) else {
            return false;
        };
        self.estimate = c;
        consistent
    }

    /// The normals the next round's bands follow, from this round's: the first three that span
    /// space (20° apart, then a volume of at least `MIN_CONSTRAINT_VOLUME`) of the constraints'
    /// normals, then the directions of single slips seen twice (a joint that gave alone slips
    /// along the normal of the face it left through; a chord that leaves through the faces of
    /// two joints still shows one of them), then the normals followed so far. The next round's bands, along their dual directions, then load one
    /// joint each, and their chords cross one pair of faces each.
    fn learn_normals(&mut self) {
        let constraints = self.strict.map(|c| c.map(|(n, _)| n));
        let slips: [Option<Vector3<f64>>; 6] = [0, 1, 2, 3, 4, 5].map(|i| self.slips[i / 2][i % 2]);
        // A slip counts where another slip or a constraint of the round went its way too (one
        // joint giving again); two joints giving together rarely mix the same way twice.
        let repeated = |i: usize, u: &Vector3<f64>| {
            let others = slips
                .iter()
                .enumerate()
                .filter(|&(j, _)| j != i)
                .map(|(_, v)| v);
            others
                .chain(constraints.iter())
                .flatten()
                .any(|v| u.dot(v).abs() >= SAME_FACES)
        };
        let candidates = constraints
            .into_iter()
            .chain(
                slips
                    .iter()
                    .enumerate()
                    .map(|(i, u)| u.filter(|u| repeated(i, u))),
            )
            .chain(self.normals.map(Some))
            .flatten();
        let mut learned = [Vector3::zeros(); 3];
        let mut count = 0;
        for n in candidates {
            let fresh = match count {
                0 => true,
                1 => n.dot(&learned[0]).abs() < SAME_FACES,
                2 => {
                    let rows = Matrix3::from_rows(&[
                        learned[0].transpose(),
                        learned[1].transpose(),
                        n.transpose(),
                    ]);
                    rows.determinant().abs() >= MIN_CONSTRAINT_VOLUME
                }
                _ => false,
            };
            if fresh {
                learned[count] = n;
                count += 1;
            }
        }
        let volume = Matrix3::from_rows(&learned.map(|n| n.transpose())).determinant();
        if count == 3 && volume.abs() >= MIN_CONSTRAINT_VOLUME {
            self.normals = learned;
        }
    }

    /// The stick region's half-width along each axis through its centre, N: where the axis
    /// first meets a pair of faces (for faces normal to the axes, their half-distance).
    fn axis_friction(&self) -> Vector3<f64> {
        Vector3::from_fn(|a, _| {
            (0..3)
                .filter(|&k| self.normals[k][a].abs() > 1e-9)
                .map(|k| self.faces[k] / self.normals[k][a].abs())
                .fold(f64::INFINITY, f64::min)
        })
        .map(|w| if w.is_finite() { w } else { 0.0 })
    }

    /// The push toward the vertex: if the handle moves, it was friction (F̂ keeps the push,
    /// and the handle settles again); if it does not under the whole push, the vertex is
    /// unreachable.
    fn push(&mut self, s: &DeviceState, mut push: Push) -> ControlOutput {
        let t = s.time;
        if let Some(failure) = self.vertex_timed_out(t) {
            return self.out_of_time(s, failure);
        }
        let vertex = self.plan.path[self.vertex].position;
        let extra = push.direction * push.force(t);
        let force = self.hold_force(&vertex, s, &(self.estimate + extra));
        match push.observe(s) {
            Step::Running => {
                self.phase = Phase::Push(push);
                ControlOutput::force(force)
            }
            Step::Done(_) => {
                self.estimate += extra;
                self.settle_from(t);
                ControlOutput::force(force)
            }
            Step::Blocked { .. } => self.give_up(s, (vertex - s.position).norm(), None),
        }
    }

    /// Record the vertex and go on to the next one, which starts from this one's force
    /// (Eqs. 12, 14; already in `estimate`), or finish.
    fn vertex_done(&mut self, s: &DeviceState, vertex: Vertex, error: f64) -> ControlOutput {
        let result = VertexResult {
            vertex,
            mass: 0.0,
            force: self.estimate,
            held_force: self.estimate,
            one_sided_force: self.one_sided.unwrap_or(self.estimate),
            friction: self.band_friction,
            iterations: self.iteration,
            final_error: error,
            measured_at: self.measured_at,
            duration: s.time - self.vertex_began,
            reached: true,
            failure: None,
        };
        self.results[self.vertex] = Some(result);
        if let Some(fit) = &mut self.arm_fit {
            fit.add(&self.measured_at, &self.estimate);
        }
        self.last_good = self.estimate;
        self.last_normals = self.normals;
        let load = self.initial.load;
        let along = if load.norm() > 0.0 {
            load.normalize()
        } else {
            Vector3::z()
        };
        self.emit(CalibrationEvent::VertexDone {
            vertex: self.vertex,
            of: self.plan.path.len(),
            mass: self.estimate.dot(&along) / self.params.g,
            force: self.estimate,
            iterations: self.iteration,
            elapsed: self.elapsed(),
        });
        self.next_vertex(s, vertex.position)
    }

    /// The current vertex could not be measured: the handle did not yield to a push toward it
    /// (`failure` None), or it did not converge (`failure`). The first time, it is approached
    /// again from beside it, from the last vertex's force, with its time and updates afresh: an
    /// obstacle on the straight way, or a hold that rang or crept from one side, need not be in
    /// the way of another. The second time, it is skipped.
    fn give_up(
        &mut self,
        s: &DeviceState,
        distance: f64,
        failure: Option<CalibrationFailure>,
    ) -> ControlOutput {
        // An explored workspace's map already knows where the handle can go.
        if self.retried || self.explorer.is_some() {
            return self.skip(s, distance, failure);
        }
        self.retried = true;
        // What a failed attempt's bands learnt may be as wrong as its F̂.
        self.normals = self.last_normals;
        let vertex = self.plan.path[self.vertex];
        let beside = self.beside(&vertex.position, &self.approach);
        self.emit(CalibrationEvent::VertexRetried {
            vertex: self.vertex,
            at: vertex,
            failure,
            beside,
        });
        self.estimate = self.last_good;
        self.gain_scale = 1.0;
        // Back to where the first approach began (a point the handle reached), then beside the
        // vertex, then to it.
        let (back, from) = (self.approach, s.position);
        self.fresh_attempt();
        let path = self.glide(from, back, s.time);
        // The vertex's time starts once it is reached again.
        self.vertex_start = s.time
            + path.duration
            + self.glide(back, beside, 0.0).duration
            + self.glide(beside, vertex.position, 0.0).duration;
        self.phase = Phase::Move {
            path,
            walked: false,
            then: [Some(beside), Some(vertex.position)],
        };
        ControlOutput::force(self.hold_force(&from, s, &self.estimate))
    }

    /// A minimum-jerk glide from `from` to `to` starting at `t`, `move_time` per cell.
    fn glide(&self, from: Vector3<f64>, to: Vector3<f64>, t: f64) -> Glide {
        Glide {
            from,
            to,
            start: t,
            duration: self.params.move_time * ((to - from).norm() / self.params.spacing).max(1.0),
        }
    }

    /// A point half a cell beside `vertex`, across the straight way the handle came from
    /// `approach`: along the axis most nearly square to that way, on the side inside the box the
    /// grid spans (with at least two vertices along every axis, one side is), toward the grid's
    /// centre if both are; inside the workspace, m.
    fn beside(&self, vertex: &Vector3<f64>, approach: &Vector3<f64>) -> Vector3<f64> {
        let way = vertex - approach;
        let a = (0..3)
            .min_by(|&i, &j| way[i].abs().total_cmp(&way[j].abs()))
            .unwrap_or(0);
        let step = axis(a) * (0.5 * self.params.spacing);
        let lo = self.plan.origin[a];
        let hi = lo + self.plan.dims[a].saturating_sub(1) as f64 * self.params.spacing;
        let inside = |x: f64| x >= lo - 1e-9 && x <= hi + 1e-9;
        let (plus, minus) = (vertex + step, vertex - step);
        let chosen = match (inside(plus[a]), inside(minus[a])) {
            (true, false) => plus,
            (false, true) => minus,
            _ if self.params.centre[a] >= vertex[a] => plus,
            _ => minus,
        };
        let (min, max) = self.params.workspace;
        chosen.zip_zip_map(&min, &max, |x, lo, hi| x.clamp(lo, hi))
    }

    /// Mark the current vertex as not measured (the handle stays `distance` m away; `failure`
    /// None: it did not yield to a push), go back to the last vertex's force and go on. Its
    /// values are filled from its neighbours once the run is over.
    fn skip(
        &mut self,
        s: &DeviceState,
        distance: f64,
        failure: Option<CalibrationFailure>,
    ) -> ControlOutput {
        let vertex = self.plan.path[self.vertex];
        self.results[self.vertex] = Some(VertexResult {
            vertex,
            mass: 0.0,
            force: Vector3::zeros(),
            held_force: Vector3::zeros(),
            one_sided_force: Vector3::zeros(),
            friction: Vector3::zeros(),
            iterations: self.iteration,
            final_error: distance,
            measured_at: vertex.position,
            duration: s.time - self.vertex_began,
            reached: false,
            failure,
        });
        self.emit(CalibrationEvent::VertexUnreachable {
            vertex: self.vertex,
            of: self.plan.path.len(),
            at: vertex,
            distance,
            failure,
            retried: self.retried,
            elapsed: self.elapsed(),
        });
        self.normals = self.last_normals;
        self.estimate = self.last_good;
        self.gain_scale = 1.0;
        self.next_vertex(s, s.position)
    }

    fn next_vertex(&mut self, s: &DeviceState, from: Vector3<f64>) -> ControlOutput {
        self.vertex += 1;
        self.retried = false;
        let of = self.plan.path.len();
        let read = self.results.iter().flatten().filter(|r| r.reached).count();
        // Fewer than half of the vertices measured (or certain to be) is too few to fill in the
        // others.
        let missed = self.vertex - read;
        if self.vertex == of || missed > of - of.div_ceil(2) {
            self.end_time = s.time;
            if read < of.div_ceil(2) {
                // Why the first vertex that was not measured failed, if it was not a stop: it
                // says what to change (a time limit, ε_M, the updates allowed).
                let first = self.results.iter().flatten().find_map(|r| r.failure);
                return self
                    .fail(first.unwrap_or(CalibrationFailure::TooFewVertices { missed, of }));
            }
            self.phase = Phase::Finished;
            self.emit(CalibrationEvent::Finished);
            return ControlOutput::done(Vector3::zeros());
        }
        self.start_move(from, s.time);
        ControlOutput::force(self.hold_force(&from, s, &self.estimate))
    }

    /// Exploration (`calibration.workspace = "explore"`): the explorer's probes, then the grid
    /// replanned on what they found, and its first vertex.
    fn explore(&mut self, s: &DeviceState) -> ControlOutput {
        // Without an explorer (never built so) the cube's plan stands and its vertices follow.
        let (force, probed) = match &mut self.explorer {
            Some(explorer) => {
                let force = explorer.tick(s, &self.gains, &self.initial.load);
                let probed = explorer.take_probe().map(|p| (explorer.probes().0 - 1, p));
                (force, probed)
            }
            None => (None, None),
        };
        if let Some((probe, p)) = probed {
            self.emit(CalibrationEvent::Probed {
                probe,
                from: p.from,
                direction: p.direction,
                run: p.run,
                stopped: p.stopped,
            });
        }
        if let Some(force) = force {
            return ControlOutput::force(force);
        }
        if let Some(explorer) = &self.explorer {
            let map = explorer.map();
            if let Err(failure) = self.plan.explore(map, self.params.spacing) {
                return self.fail(failure);
            }
            let (probes, stopped) = explorer.probes();
            let reached = map.reached();
            self.results.clear();
            self.results.resize(self.plan.path.len(), None);
            self.emit(CalibrationEvent::Explored {
                probes,
                stopped,
                reached,
                vertices: self.plan.path.len(),
                extrapolated: self.plan.extrapolated.len(),
                dims: self.plan.dims,
            });
        }
        self.vertex = 0;
        self.start_move(s.position, s.time);
        ControlOutput::force(self.hold_force(&s.position, s, &self.estimate))
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
}

/// The kinds of step whose device time [`TimeSpent`] adds up.
#[derive(Clone, Copy, Debug, PartialEq)]
enum StepKind {
    Initialisation,
    Exploration,
    Move,
    Rest,
    Band,
    Stroke,
}

impl Calibration {
    /// The kind of step the current phase is (None once the run is over).
    fn step_kind(&self) -> Option<StepKind> {
        Some(match self.phase {
            Phase::Start
            | Phase::Catch(_)
            | Phase::InitBand(_)
            | Phase::Recentre { .. }
            | Phase::Pulse(_)
            | Phase::InitStrokes(_) => StepKind::Initialisation,
            Phase::Explore => StepKind::Exploration,
            Phase::Move { .. } => StepKind::Move,
            Phase::Settle { .. } | Phase::Push(_) => StepKind::Rest,
            Phase::Band { .. } | Phase::Check { .. } => StepKind::Band,
            Phase::Strokes { .. } => StepKind::Stroke,
            Phase::Finished | Phase::Failed(_) => return None,
        })
    }

    /// Device time since the run began, s.
    fn elapsed(&self) -> f64 {
        self.last_tick.map_or(0.0, |t| t - self.start_time)
    }

    /// Adds the device time since the last tick to the kind of step the run has been in; while
    /// the run is at X_C, the reading also goes to the meter of the encoder's step.
    fn account(&mut self, state: &DeviceState) {
        let dt = self
            .last_tick
            .map_or(0.0, |last| (state.time - last).max(0.0));
        self.last_tick = Some(state.time);
        let Some(kind) = self.step_kind() else {
            return;
        };
        let spent = &mut self.time_spent;
        *match kind {
            StepKind::Initialisation => &mut spent.initialisation,
            StepKind::Exploration => &mut spent.exploration,
            StepKind::Move => &mut spent.moves,
            StepKind::Rest => &mut spent.rests,
            StepKind::Band => &mut spent.bands,
            StepKind::Stroke => &mut spent.strokes,
        } += dt;
        if kind == StepKind::Initialisation {
            self.moving.push(&state.position);
        }
    }
}

/// The unit vector along axis `a`.
fn axis(a: usize) -> Vector3<f64> {
    let mut e = Vector3::zeros();
    e[a] = 1.0;
    e
}

impl Controller for Calibration {
    fn tick(&mut self, state: &DeviceState) -> ControlOutput {
        self.account(state);
        let mut s = *state;
        s.velocity = self.filter.update(&s.position);
        let s = &s;
        self.smoothed = self.smoother.push(&s.position);
        match self.phase {
            Phase::Start => self.start(s),
            Phase::Catch(field) => self.catch(s, field),
            Phase::InitBand(probe) => self.init_band(s, probe),
            Phase::Recentre {
                axis,
                excess,
                since,
            } => self.recentre(s, axis, excess, since),
            Phase::Pulse(pulse) => self.pulse(s, pulse),
            Phase::Move { path, walked, then } => self.move_to_vertex(s, path, walked, then),
            Phase::Settle { since } => self.settle(s, since),
            Phase::Band {
                probe,
                round_start,
                anchor,
            } => self.band(s, probe, round_start, anchor),
            Phase::Push(push) => self.push(s, push),
            Phase::Check { anchor, since } => self.check(s, anchor, since),
            Phase::InitStrokes(strokes) => self.init_strokes(s, strokes),
            Phase::Explore => self.explore(s),
            Phase::Strokes { strokes, run } => self.strokes(s, strokes, run),
            Phase::Finished | Phase::Failed(_) => ControlOutput::done(Vector3::zeros()),
        }
    }
}
