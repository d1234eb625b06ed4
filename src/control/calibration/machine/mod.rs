//! The calibration controller: a state machine with one method per phase, which `tick` only
//! dispatches to. Start → Catch → InitBand (x, y, z) → (Recentre → Pulse) per axis → Recentre →
//! InitStrokes → (Move → Settle ⇄ Band / Push → Strokes) per vertex → Finished, or Failed from
//! any phase. Under friction, a vertex whose force the vertices measured before it predict
//! ([`Calibration::predicted_force`]) goes from Move straight to Strokes; with a
//! [`super::Prior`] (`hgcd check`) the initialisation ends at Catch and every vertex does.
//!
//! Like every [`Controller`], it runs on the servo thread: it must not allocate, lock, block or
//! log, so progress leaves through a bounded channel with `try_send`.
//!
//! This file holds the state, the result and the dispatch; the phases' methods live beside it:
//! `initialise.rs` (Start to InitStrokes, at X_C), `visit.rs` (Move and Settle, the updates of
//! F̂, a vertex done, retried or skipped, the next one, Explore) and `hold.rs` (Band, Check,
//! Push and Strokes: the holding force read through friction).

mod hold;
mod initialise;
mod visit;

use crossbeam_channel::Sender;
use nalgebra::{Matrix3, Vector3};

use super::explore::{self, Explorer};
use super::outcome::{
    CalibrationFailure, CalibrationResult, InitialMeasurement, TimeSpent, VertexResult,
};
use super::plan::{GridPlan, PlanError, Vertex};
use super::probe::{BandProbe, Pulse, Push, Ramp, Smoother, Step, Stroke, Stroked, Strokes};
use super::CalibrationParams;
use crate::config::WorkspaceMode;
use crate::control::pd::{AxisGains, PointHold};
use crate::control::{minimum_jerk, ControlOutput, Controller, DeviceState};
use crate::estimate::steady::{NoiseMeter, SteadyState};
use crate::estimate::Foaw;
use crate::fit::lattice;
use crate::fit::predict::ArmPrediction;

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
/// A pulse pushed by its excess plus what the bands' load and friction overstate (the survey
/// strokes' load and sliding friction say by how much): the moving mass is scaled by that share
/// of the excess where it lies within these bounds (beyond them the pulse did not push as the
/// strokes say, and its reading is kept).
const PULSE_SHARES: std::ops::RangeInclusive<f64> = 0.1..=10.0;
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
        self.from + (self.to - self.from) * minimum_jerk(self.progress(t)).0
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
    /// The force beyond the bands' load and friction each moving-mass pulse pushed with, N.
    timed_excess: Vector3<f64>,
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
    /// Where each band of the round was measured ([`Band::at`](super::probe::Band::at)), and
    /// where the vertex's force was measured (the mean over the bands, and over the rounds
    /// averaged), m.
    band_at: [Vector3<f64>; 3],
    measured_at: Vector3<f64>,
    /// The round's constraints on the holding force, one per band
    /// ([`Band::constraint`](super::probe::Band::constraint)), and the directions its slips went
    /// ([`Band::slips`](super::probe::Band::slips)).
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
                sliding_friction: None,
                inertia: Vector3::zeros(),
                noise: 0.0,
                step: 0.0,
                stiffness: Vector3::zeros(),
            },
            timed_excess: Vector3::zeros(),
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
            ordered[flat] = Some(VertexResult::not_reached(vertex));
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
