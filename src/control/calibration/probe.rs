//! The two measurements calibration makes by pushing the handle rather than waiting for it:
//!
//! - [`BandProbe`], the stick band along one direction (an axis, or a direction that loads a
//!   single joint of a linkage: see [`Band::constraint`]). A force added along it grows until the
//!   handle slips, first one way to reach the band's lower edge, then across the whole band to its
//!   upper edge, then back across it to the lower edge again; after each slip the force is held
//!   until the handle is at rest. The force at each slip is an edge of the band: its middle is
//!   the holding force along that axis, its half-width the friction. The last two crossings start
//!   at rest from opposite edges and mirror each other, so whatever the slip detection lags (the
//!   ramp, the handle's inertia) is the same on both sides and cancels in the middle. A
//!   frictionless handle slips at once: both edges are the holding force.
//! - [`Pulse`], the moving mass along one axis: a constant force a known amount beyond the stick
//!   band accelerates the handle from rest; the times it takes to cover a quarter and all of a
//!   short distance give the acceleration, whatever the delay before it starts.
//! - [`Strokes`], the holding force at a point to a millinewton despite friction: the handle is
//!   driven through the point at a constant speed along three directions (or, on an arm, along
//!   one that turns every joint), one way and back. Sliding friction opposes the motion, so it
//!   flips between the two passes and cancels in their mean; so does any lag of the slip
//!   detection or the encoder's steps, which decide a band's edges.
//!
//! All are allocation-free sub-machines the calibration controller ticks.

use nalgebra::{Matrix2, Matrix3, Vector2, Vector3};

use crate::arm::Arm;
use crate::control::{minimum_jerk, DeviceState};

/// Samples averaged to tell a slip from position noise, and to read the force at the slip.
const SLIP_WINDOW: usize = 8;

/// Samples the hold at rest averages its position over (see [`Smoother`]).
const SMOOTHING: usize = 8;

/// How a ramp of added force grows: at a constant `rate` (N/s) over its first `steady` N, so that
/// crossings of the expected band all cross their edges alike, then at a rate growing as
/// e^(t/growth), so that a wider band or an obstacle is crossed in a bounded time. A crossing
/// longer than `limit` (N) finds no slip.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct Ramp {
    pub rate: f64,
    pub steady: f64,
    pub growth: f64,
    pub limit: f64,
}

impl Ramp {
    /// Force added `t` s after the start, N.
    fn at(&self, t: f64) -> f64 {
        let t = t.max(0.0);
        let t_steady = self.steady / self.rate;
        if t <= t_steady {
            self.rate * t
        } else {
            self.steady + self.rate * self.growth * ((t - t_steady) / self.growth).exp_m1()
        }
    }
}

/// A position along one axis, smoothed over the last [`SLIP_WINDOW`] samples.
#[derive(Clone, Copy, Debug)]
struct Window {
    positions: [f64; SLIP_WINDOW],
    len: usize,
    next: usize,
}

impl Window {
    fn new() -> Self {
        Self {
            positions: [0.0; SLIP_WINDOW],
            len: 0,
            next: 0,
        }
    }

    fn push(&mut self, position: f64) {
        self.positions[self.next] = position;
        self.next = (self.next + 1) % SLIP_WINDOW;
        self.len = (self.len + 1).min(SLIP_WINDOW);
    }

    fn position(&self) -> f64 {
        self.positions[..self.len].iter().sum::<f64>() / self.len as f64
    }
}

/// The mean of the last [`SMOOTHING`] positions: what a hold at rest pulls on, so that the
/// encoder's steps and noise do not shake a stuck handle.
#[derive(Clone, Copy, Debug)]
pub(super) struct Smoother {
    samples: [Vector3<f64>; SMOOTHING],
    len: usize,
    next: usize,
}

impl Smoother {
    pub fn new() -> Self {
        Self {
            samples: [Vector3::zeros(); SMOOTHING],
            len: 0,
            next: 0,
        }
    }

    /// Add a sample; the mean of the newest ones.
    pub fn push(&mut self, x: &Vector3<f64>) -> Vector3<f64> {
        self.samples[self.next] = *x;
        self.next = (self.next + 1) % SMOOTHING;
        self.len = (self.len + 1).min(SMOOTHING);
        self.samples[..self.len].iter().sum::<Vector3<f64>>() / self.len as f64
    }
}

/// Which crossing a band probe is making.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Crossing {
    /// Toward −axis, to reach the lower edge from wherever the handle rests.
    Reach,
    /// Toward +axis, across the band from its lower edge.
    Up,
    /// Toward −axis, across the band from its upper edge.
    Down,
}

impl Crossing {
    fn sign(self) -> f64 {
        match self {
            Crossing::Up => 1.0,
            Crossing::Reach | Crossing::Down => -1.0,
        }
    }
}

/// The stick band along one direction (unit): the commanded forces at its two edges, and how
/// the handle moved when it slipped at each (from rest to rest, m).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct Band {
    pub direction: Vector3<f64>,
    pub upper: Vector3<f64>,
    pub lower: Vector3<f64>,
    pub upper_slip: Vector3<f64>,
    pub lower_slip: Vector3<f64>,
    /// Where the band was measured, m: the mean of the rests the two crossings started from
    /// (each edge is the force that moved the handle from there, so their middle is the
    /// holding force about halfway between).
    pub at: Vector3<f64>,
}

impl Band {
    /// The middle of the band along its direction (for an axis: the holding force's component
    /// there), N.
    pub fn middle(&self) -> f64 {
        self.direction.dot(&self.midpoint())
    }

    /// The middle of the chord the band was measured along: the mean of its two edges, N.
    pub fn midpoint(&self) -> Vector3<f64> {
        0.5 * (self.upper + self.lower)
    }

    /// What the band says about the holding force c, if the chord left the stick region through
    /// two opposite faces: n·c = n·(upper + lower)/2.
    ///
    /// A handle slips along the normal of the stick region's boundary where its force meets it:
    /// with joint Coulomb friction |J_iᵀ(F − c)| ≤ τ_i the region is a parallelepiped and the
    /// handle moves along the column J_i of the joint i that gives, which is the normal of that
    /// joint's two faces; a ball of friction lets it go away from its centre. The region is
    /// symmetric about c, so where the chord leaves through the two faces of one joint (the two
    /// slips are opposite), n = the difference of the slips' directions is their normal and
    /// n·c = n·(upper + lower)/2, however the chord cuts them (along a ball's chord, n is the
    /// chord's direction). A chord that leaves through the faces of two different joints (near
    /// a corner of a skewed parallelepiped) slips two ways that are not opposite: its middle
    /// says nothing exact about c, and there is no constraint (even where the difference of
    /// the slips happens to lie along the chord, as a ball's off its centre does: see
    /// [`Band::loose_constraint`], for bands before joint friction shows).
    pub fn constraint(&self) -> Option<(Vector3<f64>, f64)> {
        let up = self.upper_slip.try_normalize(1e-12)?;
        let down = self.lower_slip.try_normalize(1e-12)?;
        let n = (up - down).try_normalize(1e-12)?;
        (up.dot(&down) <= -OPPOSITE_SLIPS).then(|| (n, n.dot(&self.midpoint())))
    }

    /// The directions the handle slipped along at the two edges, both turned to point along the
    /// band's direction (None where it did not move clearly): each is the normal of the face it
    /// left through, if one joint gave.
    pub fn slips(&self) -> [Option<Vector3<f64>>; 2] {
        [self.upper_slip, -self.lower_slip].map(|v| v.try_normalize(1e-12))
    }

    /// The constraint before joint friction shows: n the difference of the slips' directions
    /// whatever they are (a ball's chord off its centre), unless more than 60° off the band's
    /// direction or without a clear slip: the direction itself.
    pub fn loose_constraint(&self) -> (Vector3<f64>, f64) {
        let unit = |v: Vector3<f64>| v.try_normalize(1e-12).unwrap_or_else(Vector3::zeros);
        let mut n = unit(unit(self.upper_slip) - unit(self.lower_slip));
        if n.dot(&self.direction) < 0.5 {
            n = self.direction;
        }
        (n, n.dot(&self.midpoint()))
    }

    /// Half the band's width along its direction: the friction there, N (0 without friction;
    /// the slip detection's lag makes it read a little wide).
    pub fn half_width(&self) -> f64 {
        (0.5 * self.direction.dot(&(self.upper - self.lower))).max(0.0)
    }
}

/// Two slips count as opposite (through the two faces of one joint) when the angle between
/// them is within 20° of 180° (the encoder's steps make a short slip's direction a little
/// uncertain; the columns of a linkage's Jacobian are further apart: the delta's come within 34°).
const OPPOSITE_SLIPS: f64 = 0.94;

/// What a probe did this tick.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) enum Step<T> {
    /// Still measuring.
    Running,
    Done(T),
    /// The handle did not move along `sign` × axis under the ramp's whole `limit`.
    Blocked {
        sign: f64,
    },
}

/// Measures the stick band along one direction (module docs). The controller adds
/// [`BandProbe::offset`] along the direction to its hold force and reports every tick's position
/// and commanded force to [`BandProbe::observe`]. Slips are watched along the same direction: a
/// handle that gives way to a push moves along it (friction only dissipates), whichever joint
/// gives.
#[derive(Clone, Copy, Debug)]
pub(super) struct BandProbe {
    /// Which band of the round (the controller's numbering), and its unit direction.
    index: usize,
    direction: Vector3<f64>,
    ramp: Ramp,
    /// Displacement of the smoothed position that counts as a slip, m.
    slip: f64,
    crossing: Crossing,
    /// Added force at the start of the crossing, N, and the start time, s.
    start_offset: f64,
    start_time: f64,
    offset: f64,
    /// Smallest progress (sign × smoothed position) since the crossing started, m.
    low: f64,
    /// How far above `low` a single reading may lie and still count as not moved, m (half an
    /// encoder step and some noise).
    still: f64,
    /// The force commanded at the last reading that had not moved: the edge, once the slip is
    /// confirmed (a slip is confirmed only after `slip`, which an encoder step or noise may make
    /// take a while).
    departure: Vector3<f64>,
    window: Window,
    upper: Vector3<f64>,
    lower: Vector3<f64>,
    /// The smoothed position where the crossing started from rest, and the moves of the Up and
    /// Down crossings' slips, m.
    start_position: Vector3<f64>,
    /// The rests the Up and Down crossings started from, m.
    up_from: Vector3<f64>,
    down_from: Vector3<f64>,
    upper_slip: Vector3<f64>,
    lower_slip: Vector3<f64>,
    /// After a slip: the added force is held until the handle is at rest again, so that every
    /// crossing starts from rest (a heavy handle would otherwise start the next one still
    /// moving, and the two crossings would not mirror each other).
    pause: Option<Pause>,
}

/// Waiting for rest before `next` (`None`: the band is measured): samples since the last block
/// mean, and that mean.
#[derive(Clone, Copy, Debug)]
struct Pause {
    next: Option<Crossing>,
    count: usize,
    previous: Option<f64>,
    /// Sum of the smoothed positions of the current block, and the previous block's mean.
    sum: Vector3<f64>,
    previous_mean: Vector3<f64>,
}

impl BandProbe {
    pub fn new(
        index: usize,
        direction: Vector3<f64>,
        ramp: Ramp,
        slip: f64,
        still: f64,
        now: f64,
    ) -> Self {
        Self {
            index,
            direction,
            ramp,
            slip,
            still,
            departure: Vector3::zeros(),
            crossing: Crossing::Reach,
            start_offset: 0.0,
            start_time: now,
            offset: 0.0,
            low: f64::INFINITY,
            window: Window::new(),
            upper: Vector3::zeros(),
            lower: Vector3::zeros(),
            start_position: Vector3::zeros(),
            up_from: Vector3::zeros(),
            down_from: Vector3::zeros(),
            upper_slip: Vector3::zeros(),
            lower_slip: Vector3::zeros(),
            pause: None,
        }
    }

    pub fn index(&self) -> usize {
        self.index
    }

    pub fn direction(&self) -> Vector3<f64> {
        self.direction
    }

    /// The force to add along the direction at time `t`, N.
    pub fn offset(&mut self, t: f64) -> f64 {
        if self.pause.is_none() {
            let sign = self.crossing.sign();
            self.offset = self.start_offset + sign * self.ramp.at(t - self.start_time);
        }
        self.offset
    }

    /// Feed the tick's state, the smoothed position and the force commanded at this tick (with
    /// its offset).
    pub fn observe(
        &mut self,
        s: &DeviceState,
        smoothed: &Vector3<f64>,
        commanded: &Vector3<f64>,
    ) -> Step<Band> {
        let along = s.position.dot(&self.direction);
        self.window.push(along);
        if self.low == f64::INFINITY {
            self.start_position = *smoothed;
        }
        if let Some(mut pause) = self.pause {
            // At rest once two consecutive block means agree within a third of a slip; where it
            // rests is the mean over both blocks.
            pause.count += 1;
            pause.sum += smoothed;
            if pause.count >= SLIP_WINDOW {
                pause.count = 0;
                let mean = self.window.position();
                let block = pause.sum / SLIP_WINDOW as f64;
                pause.sum = Vector3::zeros();
                if pause
                    .previous
                    .is_some_and(|p| (mean - p).abs() < self.slip / 3.0)
                {
                    let rest = 0.5 * (block + pause.previous_mean);
                    let moved = rest - self.start_position;
                    self.start_position = rest;
                    match self.crossing {
                        Crossing::Up => self.upper_slip = moved,
                        Crossing::Down => self.lower_slip = moved,
                        Crossing::Reach => {}
                    }
                    let Some(next) = pause.next else {
                        return Step::Done(Band {
                            direction: self.direction,
                            upper: self.upper,
                            lower: self.lower,
                            upper_slip: self.upper_slip,
                            lower_slip: self.lower_slip,
                            at: 0.5 * (self.up_from + self.down_from),
                        });
                    };
                    match next {
                        Crossing::Up => self.up_from = rest,
                        Crossing::Down => self.down_from = rest,
                        Crossing::Reach => {}
                    }
                    self.pause = None;
                    self.crossing = next;
                    self.start_offset = self.offset;
                    self.start_time = s.time;
                    self.low = next.sign() * mean;
                    return Step::Running;
                }
                pause.previous = Some(mean);
                pause.previous_mean = block;
            }
            self.pause = Some(pause);
            return Step::Running;
        }
        let sign = self.crossing.sign();
        let progress = sign * self.window.position();
        self.low = self.low.min(progress);
        if sign * along <= self.low + self.still {
            self.departure = *commanded;
        }
        if progress - self.low <= self.slip {
            return if (self.offset - self.start_offset).abs() > self.ramp.limit {
                Step::Blocked { sign }
            } else {
                Step::Running
            };
        }
        let edge = self.departure;
        let next = match self.crossing {
            Crossing::Reach => Some(Crossing::Up),
            Crossing::Up => {
                self.upper = edge;
                Some(Crossing::Down)
            }
            Crossing::Down => {
                self.lower = edge;
                None
            }
        };
        self.pause = Some(Pause {
            next,
            count: 0,
            previous: None,
            sum: Vector3::zeros(),
            previous_mean: Vector3::zeros(),
        });
        Step::Running
    }
}

/// A growing push along a unit `direction` until the handle moves along it (friction it can
/// overcome) or the ramp's limit (an obstacle): what tells a friction band from a stop.
#[derive(Clone, Copy, Debug)]
pub(super) struct Push {
    pub direction: Vector3<f64>,
    ramp: Ramp,
    slip: f64,
    start_time: f64,
    force: f64,
    low: f64,
    window: Window,
}

impl Push {
    pub fn new(direction: Vector3<f64>, ramp: Ramp, slip: f64, now: f64) -> Self {
        Self {
            direction,
            ramp,
            slip,
            start_time: now,
            force: 0.0,
            low: f64::INFINITY,
            window: Window::new(),
        }
    }

    /// The push at time `t`, N.
    pub fn force(&mut self, t: f64) -> f64 {
        self.force = self.ramp.at(t - self.start_time);
        self.force
    }

    /// Feed a tick: done (with the push that moved the handle, N) once it has moved along the
    /// direction; blocked once the push passes the ramp's limit without moving it.
    pub fn observe(&mut self, s: &DeviceState) -> Step<f64> {
        self.window.push(s.position.dot(&self.direction));
        let progress = self.window.position();
        self.low = self.low.min(progress);
        if progress - self.low > self.slip {
            Step::Done(self.force)
        } else if self.force > self.ramp.limit {
            Step::Blocked { sign: 1.0 }
        } else {
            Step::Running
        }
    }
}

/// Measures the moving mass along one axis (module docs): the controller applies the stick
/// band's middle plus `friction + excess` along +axis, and feeds each tick here.
#[derive(Clone, Copy, Debug)]
pub(super) struct Pulse {
    pub axis: usize,
    /// Force beyond the stick band's edge, N.
    pub excess: f64,
    /// Distance over which the acceleration is timed, m.
    distance: f64,
    timeout: f64,
    start_position: f64,
    start_time: f64,
    quarter_time: Option<f64>,
}

impl Pulse {
    pub fn new(
        axis: usize,
        excess: f64,
        distance: f64,
        timeout: f64,
        start: &Vector3<f64>,
        now: f64,
    ) -> Self {
        Self {
            axis,
            excess,
            distance,
            timeout,
            start_position: start[axis],
            start_time: now,
            quarter_time: None,
        }
    }

    /// Feed a tick: the moving mass (kg) once the handle has covered the distance; blocked if it
    /// has not within the time limit (the push was too weak).
    pub fn observe(&mut self, s: &DeviceState) -> Step<f64> {
        let x = s.position[self.axis] - self.start_position;
        if self.quarter_time.is_none() && x >= 0.25 * self.distance {
            self.quarter_time = Some(s.time);
        }
        if let (Some(quarter), true) = (self.quarter_time, x >= self.distance) {
            // x = a (t − t₀)² / 2: a quarter of the distance at √(d / 2a), all of it at √(2d / a),
            // so the time between them is √(d / 2a).
            let dt = (s.time - quarter).max(1e-6);
            let a = self.distance / (2.0 * dt * dt);
            return Step::Done(self.excess / a);
        }
        if s.time - self.start_time > self.timeout {
            return Step::Blocked { sign: 1.0 };
        }
        Step::Running
    }
}

/// The shape of a stroke: how far it goes each way from its centre, m; the window of it that
/// counts (centred on the centre), m; the time of one pass from end to end, s, and of its
/// speed's ramps at both ends, s; the time of the move from the centre out to the end where the
/// passes start, s, and back home after them, s.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct Stroke {
    reach: f64,
    window: f64,
    pass: f64,
    ramp: f64,
    out: f64,
    home: f64,
}

impl Stroke {
    /// Strokes that measure a holding force. A pass reaches 2 × 4 mm / 0.85 s = 9.4 mm/s, and
    /// the window starts 1.8 mm into the constant speed (0.19 s, several of the hold's time
    /// constants), so the handle crosses it at the set point's speed and its mean acceleration
    /// there vanishes. Shorter strokes leave a joint that the stroke barely turns stuck for
    /// longer: on the simulated PHANToM, ±2.5 mm strokes along the axes left up to 4 mN where
    /// ±4 mm leave 1.8 mN. Out and home in 0.5 s each: 9 s for three.
    pub const MEASURE: Self = Self {
        reach: 4e-3,
        window: 3e-3,
        pass: 1.0,
        ramp: 0.15,
        out: 0.5,
        home: 0.5,
    };
    /// [`Self::MEASURE`] for the one stroke along an arm ([`Strokes::along_the_arm`]), home in
    /// 0.25 s (30 mm/s at most): nothing is measured on the way, and the vertex's next step, a
    /// move, starts from rest at the vertex. 2.75 s. (Out in 0.25 s as well, the vertex at the
    /// top of the simulated delta's cube read 0.44 % off on average over 18 runs, against
    /// 0.37 %. The three strokes keep their 0.5 s home: the force that holds a blocked hold off
    /// the vertex is read as home ends, and the test of that case,
    /// `a_force_estimate_that_holds_the_handle_far_off_is_measured_again_not_kept`, meets it
    /// only so.)
    pub const MEASURE_ALONG_THE_ARM: Self = Self {
        home: 0.25,
        ..Self::MEASURE
    };
    /// Strokes that only tell sliding friction from none, slowly enough that viscous damping
    /// up to 1 N·s/m stays under `STROKE_FRICTION` (`machine/mod.rs`): a frictionless handle's passes
    /// differ by under 0.3 mN, a frictional one's by twice its friction. 0.5 mm of window at
    /// 4 mm/s, entered 1.55 mm into the constant speed. ±2 mm of reach, so that a hold whose
    /// load estimate is off still carries the handle through the window: on the simulated
    /// PHANToM with a 0.1 N friction band, a band misread by 0.2 N at X_C offset the handle by
    /// 0.65 mm, and ±1 mm strokes never crossed their window. 9.9 s for three.
    pub const SURVEY: Self = Self {
        reach: 2e-3,
        window: 5e-4,
        pass: 1.1,
        ramp: 0.1,
        out: 0.55,
        home: 0.55,
    };

    /// The set point's offset from −reach toward +reach at time `u` into a pass, and its rate
    /// (speed ramps at both ends, constant speed between).
    fn at(&self, u: f64) -> (f64, f64) {
        let speed = 2.0 * self.reach / (self.pass - self.ramp);
        if u < self.ramp {
            let tau = u / self.ramp;
            (
                -self.reach + speed * self.ramp * ramp_distance(tau),
                speed * minimum_jerk(tau).0,
            )
        } else if u < self.pass - self.ramp {
            (
                -self.reach + speed * (0.5 * self.ramp + u - self.ramp),
                speed,
            )
        } else {
            let tau = (self.pass - u) / self.ramp;
            (
                self.reach - speed * self.ramp * ramp_distance(tau),
                speed * minimum_jerk(tau).0,
            )
        }
    }
}

/// Three independent diagonals of the axes, for [`Strokes::through_every_joint`].
const DIAGONALS: [Vector3<f64>; 3] = [
    Vector3::new(1.0, 1.0, 1.0),
    Vector3::new(1.0, -1.0, -1.0),
    Vector3::new(-1.0, 1.0, -1.0),
];

/// A window counts only with at least this many samples in it (a blocked handle gets none).
const STROKE_MIN_SAMPLES: u32 = 50;

/// Ticks either side of a sample whose velocities give its acceleration along the stroke: a
/// window counts each sample this many ticks late, with the difference of the velocities that
/// far before and after it (30 ms at 1 kHz). Shorter spans leave the velocity's noise in the
/// acceleration and fit the handle's inertia low: on the simulated delta's top vertex, whose
/// moving mass along the stroke is 0.42 kg, 10 ms spans fitted 0.18 kg, 20 ms 0.35 kg and
/// 30 ms 0.41 kg.
const ACCELERATION_LAG: usize = 15;
const HISTORY: usize = 2 * ACCELERATION_LAG + 1;

/// One tick of a pass, held back until its acceleration is known.
#[derive(Clone, Copy, Debug, Default)]
struct Sample {
    time: f64,
    position: Vector3<f64>,
    /// The velocity along the stroke, m/s.
    speed: f64,
    commanded: Vector3<f64>,
}

/// The last [`HISTORY`] ticks of the current pass.
#[derive(Clone, Copy, Debug)]
struct History {
    samples: [Sample; HISTORY],
    /// How many ticks of the pass have been pushed (the ring is full from `HISTORY` on).
    pushed: usize,
    /// The stroke and pass they belong to.
    pass: (usize, usize),
}

impl History {
    fn new() -> Self {
        Self {
            samples: [Sample::default(); HISTORY],
            pushed: 0,
            pass: (usize::MAX, 0),
        }
    }

    /// Push a tick of `pass`: the tick `ACCELERATION_LAG` before it and its acceleration along
    /// the stroke (m/s²), once the ring holds the ticks either side of it.
    fn push(&mut self, pass: (usize, usize), sample: Sample) -> Option<(Sample, f64)> {
        if pass != self.pass {
            self.pass = pass;
            self.pushed = 0;
        }
        self.samples[self.pushed % HISTORY] = sample;
        self.pushed += 1;
        if self.pushed < HISTORY {
            return None;
        }
        let oldest = self.samples[self.pushed % HISTORY];
        let centred = self.samples[(self.pushed + ACCELERATION_LAG) % HISTORY];
        let span = sample.time - oldest.time;
        (span > 0.0).then(|| (centred, (sample.speed - oldest.speed) / span))
    }
}

/// Sums over the ticks one pass spent in its window, each weighted by the window's taper (and
/// the weights' sum): of the commanded force F, the handle's position x − centre, its offset s
/// along the stroke and its acceleration a along it, and of the products a weighted
/// least-squares fit of F = α + β s + Λ a needs.
#[derive(Clone, Copy, Debug, Default)]
struct PassWindow {
    count: u32,
    weight: f64,
    force: Vector3<f64>,
    position: Vector3<f64>,
    s: f64,
    ss: f64,
    a: f64,
    sa: f64,
    aa: f64,
    force_s: Vector3<f64>,
    force_a: Vector3<f64>,
}

impl PassWindow {
    fn add(&mut self, w: f64, position: Vector3<f64>, s: f64, a: f64, force: &Vector3<f64>) {
        self.count += 1;
        self.weight += w;
        self.force += force * w;
        self.position += position * w;
        self.s += s * w;
        self.ss += s * s * w;
        self.a += a * w;
        self.sa += s * a * w;
        self.aa += a * a * w;
        self.force_s += force * (s * w);
        self.force_a += force * (a * w);
    }

    fn n(&self) -> f64 {
        self.weight
    }

    /// The sums of a² and of F a left once α + β s is fitted out of both (the acceleration's
    /// variation the offset along the stroke does not explain, and the force's along it).
    fn residual_products(&self) -> (f64, Vector3<f64>) {
        // [Σa, Σsa] G⁻¹ [Σa, Σsa]ᵀ and [ΣF, ΣFs] G⁻¹ [Σa, Σsa]ᵀ, with G = [[n, Σs], [Σs, Σss]].
        let gram = Matrix2::new(self.n(), self.s, self.s, self.ss);
        let Some(g) = gram
            .try_inverse()
            .map(|inverse| inverse * Vector2::new(self.a, self.sa))
        else {
            return (0.0, Vector3::zeros());
        };
        (
            self.aa - (self.a * g.x + self.sa * g.y),
            self.force_a - (self.force * g.x + self.force_s * g.y),
        )
    }
}

/// Distance covered from rest at progress τ of a speed ramp whose speed follows a minimum-jerk
/// profile from 0 to 1 (∫ s(τ) dτ; 1/2 at τ = 1).
fn ramp_distance(tau: f64) -> f64 {
    let t = tau.clamp(0.0, 1.0);
    t * t * t * t * (2.5 - 3.0 * t + t * t)
}

/// Which part of a stroke the set point is on.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Leg {
    /// From the centre out to −reach (not measured).
    Out,
    /// From −reach to +reach at constant speed, and back.
    Forward,
    Backward,
    /// From −reach back to the centre.
    Home,
}

/// The holding force at `centre` from strokes along three directions, or along one that turns
/// every joint of an arm (module docs). The controller holds the handle on
/// [`Strokes::set_point`] with its PD plus its force estimate, and reports every tick's
/// commanded force to [`Strokes::observe`]. Along each direction d the set
/// point goes out to −reach, passes to +reach and back at constant speed, and returns; the
/// commanded force is averaged over the ticks at which the handle itself (not the set point,
/// which it trails by the friction over the stiffness) is within half a window of the centre, so
/// that both passes average over the same stretch. Each tick is weighted by a Hann taper of its
/// offset along the stroke (1 at the centre, 0 at the window's edges), so that the handle's
/// momentum as it enters and leaves the window, which a plain mean divides by the window's time,
/// weighs nothing: on the simulated delta at 0.08 N at the handle the worst vertex of 120
/// calibrations went from 0.44 % to 0.42 % and their mean worst vertex from 0.27 % to 0.22 %
/// (at 0.02 N, 60 calibrations: 0.34 % against 0.36 %; the 2–3 mN its bottom corners read
/// off with no friction at the handle, where a plain mean read them within 2 mN, was the
/// joints' friction read where the two passes held the handle apart, which one stroke along an
/// arm takes out: [`Strokes::joint_friction_apart`]). What momentum the handle gains inside the
/// window is taken out as well ([`Strokes::pass_means`]). With F̄₊ and F̄₋ the two passes'
/// means, d·F_G = d·(F̄₊ + F̄₋)/2: sliding friction flips between them, the handle's and a
/// sliding joint's alike.
/// A joint that a stroke turns only slightly sticks for part of it, and a stuck joint's torque
/// does not flip: strokes that turn every joint of a linkage well (see
/// [`Strokes::through_every_joint`]) keep that error small. The three d·F_G give F_G. Where
/// every joint slides on both passes ([`Strokes::along_the_arm`]), nothing sticks across the
/// stroke either, and one stroke's (F̄₊ + F̄₋)/2 is all of F_G.
#[derive(Clone, Copy, Debug)]
pub(super) struct Strokes {
    stroke: Stroke,
    centre: Vector3<f64>,
    directions: [Vector3<f64>; 3],
    /// How many of `directions` are stroked: three, each giving the holding force along it, or
    /// one that turns every joint of an arm, giving all of it.
    count: usize,
    start: f64,
    /// Each direction's forward and backward windows.
    windows: [[PassWindow; 2]; 3],
    history: History,
    /// Whether the handle was seen before and beyond the window on each pass: only a pass that
    /// carried it through the whole window measured anything.
    through: [[(bool, bool); 2]; 3],
    /// The arm one stroke turns every joint of ([`Strokes::along_the_arm`]): its joints'
    /// friction is carried to where each pass was ([`Strokes::joint_friction_apart`]).
    arm: Option<Arm>,
}

/// What strokes measured: the holding force, and the sliding friction (half the difference of
/// the passes), N: along each of three strokes' directions, or, for one stroke, the whole vector
/// of the difference; and where the force was measured, m.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct Stroked {
    pub force: Vector3<f64>,
    pub friction: Vector3<f64>,
    /// Where the handle was, on average over the windows (each pass weighted as its force is):
    /// the centre, unless the hold kept the handle off the set point's line, as it does by
    /// (F_G − F̂) / K where its feedforward F̂ is off. The passes' mean force is the holding
    /// force there, not at the centre: on the simulated WoodenHaptics without friction at the
    /// handle, a first vertex's F̂ held the handle 0.3 mm off, and its force read 3 mN off the
    /// centre's.
    pub at: Vector3<f64>,
    /// For one stroke, its direction and the spread of the windows' positions along it about
    /// `at` (their mean square offset, m²): a field that curves along the stroke averages over
    /// the windows to more or less than its value at `at` ([`Stroked::less_curvature`]).
    pub spread: Option<(Vector3<f64>, f64)>,
}

/// The most [`Strokes::joint_friction_apart`] takes out, as a share of the passes' friction (it
/// took out up to 1.5 % of it on the simulated delta).
const APART_SHARE: f64 = 0.1;

/// Half the span of the central differences that give a field's curvature along a stroke, m.
const CURVATURE_STEP: f64 = 2e-3;

impl Stroked {
    /// The force measured less what the curvature of `field` (a prediction of the holding force,
    /// None where it has none) along the stroke adds to its mean over the windows: ½ F'' σ², σ²
    /// the windows' spread. At the simulated delta's top vertex, where the field steepens
    /// upward, the ±1.5 mm windows averaged it 0.97 mN above its value at the vertex.
    pub fn less_curvature(mut self, field: impl Fn(&Vector3<f64>) -> Option<Vector3<f64>>) -> Self {
        let Some((direction, spread)) = self.spread else {
            return self;
        };
        let step = direction * CURVATURE_STEP;
        let (Some(below), Some(here), Some(above)) = (
            field(&(self.at - step)),
            field(&self.at),
            field(&(self.at + step)),
        ) else {
            return self;
        };
        let curvature = (above - 2.0 * here + below) / (CURVATURE_STEP * CURVATURE_STEP);
        self.force -= 0.5 * curvature * spread;
        self
    }
}

impl Strokes {
    /// Strokes along the three unit `directions` (linearly independent).
    pub fn new(
        stroke: Stroke,
        centre: Vector3<f64>,
        directions: [Vector3<f64>; 3],
        now: f64,
    ) -> Self {
        Self {
            stroke,
            centre,
            directions,
            count: 3,
            start: now,
            windows: [[PassWindow::default(); 2]; 3],
            history: History::new(),
            through: [[(false, false); 2]; 3],
            arm: None,
        }
    }

    /// Along x, y and z: each stroke's friction is the friction along an axis.
    pub fn along_axes(stroke: Stroke, centre: Vector3<f64>, now: f64) -> Self {
        Self::new(
            stroke,
            centre,
            [Vector3::x(), Vector3::y(), Vector3::z()],
            now,
        )
    }

    /// Along the three diagonals (1, 1, 1), (1, −1, −1) and (−1, 1, −1) of the axes. On a
    /// linkage whose joints move the handle roughly along the axes, as the PHANToM's do about
    /// its home pose, each turns every joint at a good share of its rate, where a stroke along
    /// one axis may turn a joint 30 times slower than the others and leave it stuck: on the
    /// simulated PHANToM the worst vertex went from 1.8 mN to 0.5 mN. (The face normals the
    /// bands learn on a linkage would point along its joints exactly, but a few bands' slips
    /// make noisy normals, and strokes along nearly parallel ones measured worse.)
    pub fn through_every_joint(stroke: Stroke, centre: Vector3<f64>, now: f64) -> Self {
        Self::new(stroke, centre, DIAGONALS.map(|d| d.normalize()), now)
    }

    /// One stroke at `centre` along the diagonal (1, 1, 1): every axis slides on both passes, so
    /// where friction follows the push (a ball of friction, or one per axis) its friction flips
    /// and the one stroke measures all three components of the holding force.
    pub fn along_a_diagonal(stroke: Stroke, centre: Vector3<f64>, now: f64) -> Self {
        Self::along(stroke, centre, DIAGONALS[0].normalize(), now)
    }

    /// One stroke at `centre` along `direction` (a unit vector): the mean commanded force over
    /// its two windows is the whole holding force, where every joint of a linkage slides on
    /// both passes and so flips its friction (see [`Strokes::along_the_arm`]).
    pub fn along(stroke: Stroke, centre: Vector3<f64>, direction: Vector3<f64>, now: f64) -> Self {
        Self {
            count: 1,
            ..Self::new(stroke, centre, [direction; 3], now)
        }
    }

    /// One stroke at `centre` along the direction that turns every joint of `arm` at the same
    /// rate: J s with s one of (±1, ±1, ±1), J the arm's Jacobian there, whichever turns the
    /// joints fastest for the handle's speed (the shortest J s). No joint sticks, so every
    /// joint's friction flips between the passes, and the one stroke measures all three
    /// components of the holding force where three strokes along the axes' diagonals each
    /// measured one (a joint that a stroke barely turned stuck, and a stuck joint's torque
    /// adds nothing along the stroke but does across it). None where the arm does not reach
    /// `centre`.
    pub fn along_the_arm(
        stroke: Stroke,
        arm: &Arm,
        centre: Vector3<f64>,
        now: f64,
    ) -> Option<Self> {
        let j = arm.jacobian(&centre)?;
        let direction = [
            Vector3::new(1.0, 1.0, 1.0),
            Vector3::new(1.0, 1.0, -1.0),
            Vector3::new(1.0, -1.0, 1.0),
            Vector3::new(-1.0, 1.0, 1.0),
        ]
        .map(|signs| j * signs)
        .into_iter()
        .filter(|d| d.norm().is_finite() && d.norm() > 0.0)
        .min_by(|a, b| a.norm().total_cmp(&b.norm()))?;
        Some(Self {
            arm: Some(*arm),
            ..Self::along(stroke, centre, direction.normalize(), now)
        })
    }

    /// What the joints' friction adds to the passes' mean force because the two passes held
    /// the handle at different places, x₊ and x₋: a joint's friction τ flips between the passes
    /// but reaches the handle through J⁻ᵀ where each pass was, so the mean keeps
    /// ½ (J⁻ᵀ(x₊) − J⁻ᵀ(x₋)) τ, with τ = Jᵀ f from the passes' half-difference f at their
    /// middle. The handle trails its set point by the friction over the hold's stiffness, to
    /// either side of the stroke's line as the friction flips: at the simulated delta's bottom
    /// corners, where the joints' friction is 0.24 N at the handle, the passes were 0.6 mm apart
    /// across the stroke and their mean read about (−2, ±2, +2) mN off (1 % of the friction).
    /// Zero without an arm, where J is singular, or where the term would be more than
    /// [`APART_SHARE`] of the friction: the first-order picture does not hold there (a pass near
    /// a singular pose), and the plain mean is kept.
    fn joint_friction_apart(
        &self,
        places: [Vector3<f64>; 2],
        at: &Vector3<f64>,
        friction: &Vector3<f64>,
    ) -> Vector3<f64> {
        let Some(arm) = &self.arm else {
            return Vector3::zeros();
        };
        match (
            arm.jacobian(at),
            arm.to_handle(&places[0]),
            arm.to_handle(&places[1]),
        ) {
            (Some(j), Some(forward), Some(backward)) => {
                let apart = 0.5 * (forward - backward) * (j.transpose() * friction);
                if apart.norm() <= APART_SHARE * friction.norm() {
                    apart
                } else {
                    Vector3::zeros()
                }
            }
            _ => Vector3::zeros(),
        }
    }

    pub fn centre(&self) -> Vector3<f64> {
        self.centre
    }

    /// The stroke and leg at time `t`, with the set point's offset along the stroke and its rate;
    /// `None` once the strokes are over.
    fn leg(&self, t: f64) -> Option<(usize, Leg, f64, f64)> {
        let Stroke {
            reach,
            pass,
            out,
            home,
            ..
        } = self.stroke;
        let per_stroke = out + home + 2.0 * pass;
        let u = (t - self.start).max(0.0);
        let k = (u / per_stroke) as usize;
        if k >= self.count {
            return None;
        }
        let u = u - k as f64 * per_stroke;
        Some(if u < out {
            let (s, rate) = minimum_jerk(u / out);
            (k, Leg::Out, -reach * s, -reach * rate / out)
        } else if u < out + pass {
            let (x, v) = self.stroke.at(u - out);
            (k, Leg::Forward, x, v)
        } else if u < out + 2.0 * pass {
            let (x, v) = self.stroke.at(u - out - pass);
            (k, Leg::Backward, -x, -v)
        } else {
            let (s, rate) = minimum_jerk((u - out - 2.0 * pass) / home);
            (k, Leg::Home, -reach * (1.0 - s), reach * rate / home)
        })
    }

    /// The set point at time `t` and its velocity, m and m/s (the centre once over).
    pub fn set_point(&self, t: f64) -> (Vector3<f64>, Vector3<f64>) {
        match self.leg(t) {
            Some((k, _, x, v)) => {
                let d = self.directions[k];
                (self.centre + x * d, v * d)
            }
            None => (self.centre, Vector3::zeros()),
        }
    }

    /// Feed a tick and the force commanded at it: the measurement once the strokes are over,
    /// `Blocked` if a pass did not carry the handle through its window (a stop or an obstacle
    /// within reach of the centre), or if the directions are degenerate.
    pub fn observe(&mut self, s: &DeviceState, commanded: &Vector3<f64>) -> Step<Stroked> {
        let Some((k, leg, _, _)) = self.leg(s.time) else {
            return self.result();
        };
        let pass = match leg {
            Leg::Forward => 0,
            Leg::Backward => 1,
            Leg::Out | Leg::Home => return Step::Running,
        };
        let d = self.directions[k];
        let along = d.dot(&(s.position - self.centre));
        let (before, beyond) = &mut self.through[k][pass];
        let half = 0.5 * self.stroke.window;
        *before |= along < -half;
        *beyond |= along > half;
        let sample = Sample {
            time: s.time,
            position: s.position,
            speed: d.dot(&s.velocity),
            commanded: *commanded,
        };
        if let Some((centred, acceleration)) = self.history.push((k, pass), sample) {
            let offset = centred.position - self.centre;
            let along = d.dot(&offset);
            if along.abs() <= half {
                let weight = 0.5 * (1.0 + (std::f64::consts::PI * along / half).cos());
                self.windows[k][pass].add(weight, offset, along, acceleration, &centred.commanded);
            }
        }
        Step::Running
    }

    /// Each pass's mean commanded force over its window, less the force that changed the
    /// handle's momentum there: Λ ā d, with ā the pass's mean acceleration along the stroke d
    /// and Λ the handle's inertia along it (kg), fitted to both passes' swings along it,
    /// d·F = α + β s + Λ a with α and β each pass's own. (A vector Λ, fitting every component
    /// of the force to the swings, took the noise of a joint's friction across a weakly ringing
    /// stroke for 1.1 kg of cross-inertia on the simulated delta and put a vertex 4 mN off.)
    /// A hold that rings as it crosses its window (after a joint broke away at the stroke's
    /// end, on a heavy axis) gains or loses speed there, and that force does not cancel
    /// between passes that ring differently: at the simulated delta's top vertex the pass
    /// down, starting where the moving mass is largest, crossed its window slowing from 12 to
    /// 9 mm/s, 2.6 mN of the vertex's 5 mN. A fit that finds no inertia along the stroke
    /// (Λ·d ≤ 0: no swings, only noise) corrects nothing.
    fn pass_means(&self, k: usize) -> [Vector3<f64>; 2] {
        let [forward, backward] = &self.windows[k];
        let (aa_f, fa_f) = forward.residual_products();
        let (aa_b, fa_b) = backward.residual_products();
        let d = self.directions[k];
        let swings = aa_f + aa_b;
        let inertia = if swings > 0.0 {
            (d.dot(&(fa_f + fa_b)) / swings).max(0.0)
        } else {
            0.0
        };
        [forward, backward].map(|w| (w.force - d * (inertia * w.a)) / w.n())
    }

    fn result(&self) -> Step<Stroked> {
        let blocked = Step::Blocked { sign: 1.0 };
        let mut means = [[Vector3::zeros(); 2]; 3];
        let mut at = Vector3::zeros();
        for (k, mean) in means.iter_mut().enumerate().take(self.count) {
            let [forward, backward] = &self.windows[k];
            let through = self.through[k]
                .iter()
                .all(|&(before, beyond)| before && beyond);
            if !through || forward.count.min(backward.count) < STROKE_MIN_SAMPLES {
                return blocked;
            }
            *mean = self.pass_means(k);
            at += 0.5 * (forward.position / forward.n() + backward.position / backward.n());
        }
        let at = self.centre + at / self.count as f64;
        if self.count == 1 {
            let [forward, backward] = means[0];
            let friction = 0.5 * (forward - backward);
            let places = self.windows[0].map(|w| self.centre + w.position / w.n());
            let apart = self.joint_friction_apart(places, &at, &friction);
            let d = self.directions[0];
            let mid = d.dot(&(at - self.centre));
            let spread = self.windows[0]
                .iter()
                .map(|w| (w.ss - 2.0 * mid * w.s) / w.n() + mid * mid)
                .sum::<f64>()
                / 2.0;
            return Step::Done(Stroked {
                force: 0.5 * (forward + backward) - apart,
                friction,
                at,
                spread: Some((d, spread)),
            });
        }
        let mut along = Vector3::zeros();
        let mut friction = Vector3::zeros();
        for (k, [forward, backward]) in means.iter().enumerate() {
            let d = self.directions[k];
            along[k] = 0.5 * d.dot(&(forward + backward));
            friction[k] = 0.5 * d.dot(&(forward - backward));
        }
        let rows = Matrix3::from_rows(&self.directions.map(|d| d.transpose()));
        match rows.try_inverse() {
            Some(inverse) => Step::Done(Stroked {
                force: inverse * along,
                friction,
                at,
                spread: None,
            }),
            None => blocked,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn state(t: f64, x: f64) -> DeviceState {
        DeviceState {
            time: t,
            host_time: t,
            position: Vector3::new(x, 0.0, 0.0),
            velocity: Vector3::zeros(),
            status: Default::default(),
            tick: 0,
        }
    }

    /// One tick `dt` of a point of mass `m` under the net force `net` with isotropic Coulomb
    /// friction `f` (static as kinetic), in ten substeps.
    fn slide(
        x: &mut Vector3<f64>,
        v: &mut Vector3<f64>,
        net: Vector3<f64>,
        m: f64,
        f: f64,
        dt: f64,
    ) {
        let h = dt / 10.0;
        for _ in 0..10 {
            let trial = *v + net * (h / m);
            *v = if trial.norm() <= f * h / m {
                Vector3::zeros()
            } else {
                trial - trial.normalize() * (f * h / m)
            };
            *x += *v * h;
        }
    }

    /// A 1-D point of mass `m` with Coulomb friction `f` around the holding force `hold`, under
    /// a critically damped spring `k` to the origin plus the probe's offset; the probe's band.
    fn band_of(m: f64, f: f64, hold: f64, k: f64) -> Band {
        let ramp = Ramp {
            rate: 0.5,
            steady: 0.3,
            growth: 0.2,
            limit: 3.0,
        };
        let mut probe = BandProbe::new(0, Vector3::x(), ramp, 5e-6, 2e-6, 0.0);
        let (mut x, mut v) = (Vector3::zeros(), Vector3::zeros());
        let dt = 1e-3;
        for n in 0..20_000 {
            let t = n as f64 * dt;
            let force = -k * x.x - 2.0 * (k * m).sqrt() * v.x + probe.offset(t);
            match probe.observe(&state(t, x.x), &x, &Vector3::new(force, 0.0, 0.0)) {
                Step::Done(band) => return band,
                Step::Blocked { .. } => panic!("blocked"),
                Step::Running => {}
            }
            slide(
                &mut x,
                &mut v,
                Vector3::new(force - hold, 0.0, 0.0),
                m,
                f,
                dt,
            );
        }
        panic!("no band");
    }

    #[test]
    fn the_middle_of_the_band_is_the_holding_force_and_its_half_width_the_friction() {
        for (m, f, hold) in [(0.12, 0.1, 0.3), (0.5, 0.05, -1.0), (0.005, 0.0, 0.04)] {
            let band = band_of(m, f, hold, 200.0);
            assert!((band.middle() - hold).abs() < 2e-4, "{m} {f}: {band:?}");
            assert!(
                band.half_width() >= f && band.half_width() < f + 0.03,
                "{m} {f}: {band:?}"
            );
        }
    }

    /// A point of mass `m` with isotropic Coulomb friction `f` (static as kinetic) and holding
    /// force `hold`, read through an encoder of 10 µm steps, held on the strokes' set point by a
    /// PD with a feedforward `off` from the holding force; what `strokes` measure.
    fn strokes_on(
        strokes: Strokes,
        m: f64,
        f: f64,
        hold: Vector3<f64>,
        off: Vector3<f64>,
    ) -> Stroked {
        strokes_in(strokes, m, f, |_| hold, hold + off)
    }

    /// [`strokes_on`] with a holding force that depends on where the handle is, `hold(x)`, and
    /// the hold's feedforward `estimate`, constant as the calibration's is.
    fn strokes_in(
        strokes: Strokes,
        m: f64,
        f: f64,
        hold: impl Fn(&Vector3<f64>) -> Vector3<f64>,
        estimate: Vector3<f64>,
    ) -> Stroked {
        strokes_knocked(strokes, m, f, 1.0, hold, estimate, |_| Vector3::zeros())
    }

    /// [`strokes_in`] with the hold's damping ratio `zeta`, and the handle's velocity changed by
    /// `knock(t)` (m/s) at each tick t, as a tap on it would.
    fn strokes_knocked(
        mut strokes: Strokes,
        m: f64,
        f: f64,
        zeta: f64,
        hold: impl Fn(&Vector3<f64>) -> Vector3<f64>,
        estimate: Vector3<f64>,
        knock: impl Fn(f64) -> Vector3<f64>,
    ) -> Stroked {
        let (k, c) = (300.0, 2.0 * zeta * (300.0 * m).sqrt());
        let (mut x, mut v) = (strokes.centre(), Vector3::<f64>::zeros());
        let dt = 1e-3;
        for n in 0..20_000 {
            let t = n as f64 * dt;
            let reading = (x / 1e-5).map(f64::round) * 1e-5;
            let (target, target_v) = strokes.set_point(t);
            let force = (target - reading) * k - (v - target_v) * c + estimate;
            let mut s = state(t, 0.0);
            s.position = reading;
            s.velocity = v;
            match strokes.observe(&s, &force) {
                Step::Done(stroked) => return stroked,
                Step::Blocked { .. } => panic!("blocked"),
                Step::Running => {}
            }
            let net = force - hold(&x);
            slide(&mut x, &mut v, net, m, f, dt);
            v += knock(t);
        }
        panic!("never done");
    }

    /// A hold that rings as it crosses a window gains or loses momentum there, and the force
    /// that does it is no part of the holding force: the strokes read the pass's force less
    /// it. Here a lightly damped hold on 0.4 kg is tapped (+4 mm/s along the stroke) as its
    /// first pass nears the window, and crosses it still ringing; the pass back is not.
    /// Uncorrected, the strokes read 1.9 mN (friction-free) and 2.2 mN (0.05 N) off; corrected,
    /// 0.01–0.02 mN.
    #[test]
    fn a_hold_ringing_across_its_window_is_read_less_the_momentum_it_gained_there() {
        let hold = Vector3::new(0.05, -0.03, 1.2);
        let direction = Vector3::new(0.3, -0.5, 0.8).normalize();
        let centre = Vector3::new(0.01, -0.02, 0.0);
        for f in [0.0, 0.05] {
            let strokes = Strokes::along(Stroke::MEASURE, centre, direction, 0.0);
            // The first pass starts at out = 0.5 s and enters its window about 0.33 s later.
            let tap = |t: f64| {
                if (t - 0.74).abs() < 5e-4 {
                    direction * 4e-3
                } else {
                    Vector3::zeros()
                }
            };
            let stroked = strokes_knocked(strokes, 0.4, f, 0.15, |_| hold, hold, tap);
            let error = (stroked.force - hold).norm();
            assert!(error < 2e-4, "{f} N: off by {error} N");
        }
    }

    /// Over windows ±1.5 mm wide, a field that curves along the stroke averages to more than its
    /// value where they read it (1.7 mN here); a prediction of the field takes that out (0.02
    /// mN left).
    #[test]
    fn a_field_curving_along_the_stroke_is_read_at_its_centre_less_its_curvature() {
        let centre = Vector3::new(0.0, 0.0, 0.04);
        let direction = Vector3::z();
        // As the simulated delta's top vertex, 1.17 N and 26 N/m upward, but steepening by 12 N/m
        // per mm (the delta's 2.6).
        let field = |x: &Vector3<f64>| {
            let s = x.z - centre.z;
            Vector3::new(0.0, 0.0, 1.17 + 26.0 * s + 0.5 * 12000.0 * s * s)
        };
        let strokes = Strokes::along(Stroke::MEASURE, centre, direction, 0.0);
        let stroked = strokes_in(strokes, 0.12, 0.05, field, field(&centre));
        let read = (stroked.force - field(&stroked.at)).norm();
        assert!(read > 1.2e-3, "the windows' mean: {read} N over the field");
        let corrected = stroked.less_curvature(|x| Some(field(x)));
        let error = (corrected.force - field(&corrected.at)).norm();
        assert!(error < 2e-4, "off by {error} N");
        // Without a prediction, nothing changes.
        assert_eq!(stroked.less_curvature(|_| None), stroked);
    }

    /// Where the holding force changes with the position and the hold's feedforward is off, the
    /// hold keeps the handle off the set point's line, and the strokes read the holding force
    /// there: they say where (on the simulated WoodenHaptics without friction at the handle, a
    /// first vertex's feedforward held the handle 0.3 mm off, and read 3 mN off the centre's).
    #[test]
    fn strokes_say_where_they_read_the_holding_force() {
        let centre = Vector3::new(0.01, -0.02, 0.0);
        // As steep as the simulated delta's field at its top vertex (26 mN more per millimetre
        // upward).
        let gradient = Matrix3::from_diagonal(&Vector3::new(-20.0, -20.0, 26.0));
        let field = |x: &Vector3<f64>| Vector3::new(0.05, -0.03, 1.2) + gradient * (x - centre);
        let direction = Vector3::new(0.3, -0.5, 0.8).normalize();
        for (m, f) in [(0.12, 0.1), (0.05, 0.0)] {
            let strokes = Strokes::along(Stroke::MEASURE, centre, direction, 0.0);
            // 87 mN across the stroke: the handle about 0.3 mm off its line.
            let off = Vector3::new(-0.075, -0.045, 0.0);
            let stroked = strokes_in(strokes, m, f, field, field(&centre) + off);
            let at_centre = (stroked.force - field(&centre)).norm();
            let where_read = (stroked.force - field(&stroked.at)).norm();
            assert!(at_centre > 3e-3, "{m} kg, {f} N: {at_centre} N");
            assert!(where_read < 3e-4, "{m} kg, {f} N: off by {where_read} N");
        }
    }

    /// Joint friction τ that flips between two passes held 0.6 mm apart across the stroke
    /// reaches the handle through J⁻ᵀ at each place, F₊ = J⁻ᵀ(x₊) τ and F₋ = −J⁻ᵀ(x₋) τ
    /// (no other force): what the passes' mean keeps is what the arm's term takes out, to
    /// second order in their distance; without an arm, nothing is.
    #[test]
    fn the_joints_friction_read_at_two_places_is_what_the_passes_mean_keeps() {
        let arm = crate::arm::tests::delta();
        let centre = Vector3::new(0.04, -0.04, -0.04);
        let strokes = Strokes::along_the_arm(Stroke::MEASURE_ALONG_THE_ARM, &arm, centre, 0.0)
            .expect("the arm reaches the centre");
        let tau = Vector3::new(0.004, -0.004, 0.004);
        let to_handle =
            |x: &Vector3<f64>| arm.jacobian(x).unwrap().try_inverse().unwrap().transpose();
        let across = Vector3::new(-0.63, 0.59, 0.05).normalize() * 3e-4;
        let places = [centre + across, centre - across];
        let (forward, backward) = (to_handle(&places[0]) * tau, -(to_handle(&places[1]) * tau));
        let (kept, friction) = (0.5 * (forward + backward), 0.5 * (forward - backward));
        let apart = strokes.joint_friction_apart(places, &centre, &friction);
        assert!(kept.norm() > 1e-3, "the mean keeps {kept}");
        assert!(
            (kept - apart).norm() < 0.05 * kept.norm(),
            "{kept} against {apart}"
        );
        let plain = Strokes::along(Stroke::MEASURE_ALONG_THE_ARM, centre, Vector3::z(), 0.0);
        assert_eq!(
            plain.joint_friction_apart(places, &centre, &friction),
            Vector3::zeros()
        );
    }

    #[test]
    fn strokes_read_the_holding_force_through_friction_and_encoder_steps() {
        let hold = Vector3::new(0.05, -0.03, 1.2);
        for (m, f) in [(0.12, 0.1), (0.5, 0.05), (0.05, 0.0)] {
            // The estimate the hold starts from may be off by several millinewtons.
            let strokes = Strokes::along_axes(Stroke::MEASURE, Vector3::new(0.01, -0.02, 0.0), 0.0);
            let stroked = strokes_on(strokes, m, f, hold, Vector3::new(0.008, -0.005, 0.01));
            let error = (stroked.force - hold).norm();
            assert!(error < 5e-4, "{m} kg, {f} N: off by {error} N");
            for friction in stroked.friction.iter() {
                assert!((friction - f).abs() < 0.01, "{m} kg, {f} N: {stroked:?}");
            }
        }
    }

    /// Friction that flips with the motion (here the handle's, isotropic) cancels across the
    /// stroke as well as along it: one oblique stroke reads all three components, and its
    /// passes differ by twice the friction, along the stroke.
    #[test]
    fn one_stroke_reads_the_whole_holding_force_where_friction_flips_with_the_motion() {
        let hold = Vector3::new(0.05, -0.03, 1.2);
        let direction = Vector3::new(0.3, -0.5, 0.8).normalize();
        for (m, f) in [(0.12, 0.1), (0.5, 0.05), (0.05, 0.0)] {
            let strokes = Strokes::along(
                Stroke::MEASURE,
                Vector3::new(0.01, -0.02, 0.0),
                direction,
                0.0,
            );
            let stroked = strokes_on(strokes, m, f, hold, Vector3::new(0.008, -0.005, 0.01));
            let error = (stroked.force - hold).norm();
            assert!(error < 5e-4, "{m} kg, {f} N: off by {error} N");
            let sliding = stroked.friction.dot(&direction);
            assert!((sliding - f).abs() < 0.01, "{m} kg, {f} N: {stroked:?}");
            assert!(
                (stroked.friction - sliding * direction).norm() < 0.005,
                "{stroked:?}"
            );
        }
    }

    #[test]
    fn a_pulse_times_the_acceleration_whatever_the_delay() {
        // 0.05 N beyond the band on 0.2 kg: a = 0.25 m/s², starting 7 ms late.
        let mut pulse = Pulse::new(0, 0.05, 5e-4, 1.0, &Vector3::zeros(), 0.0);
        let dt = 1e-3;
        for n in 0..1000 {
            let t = n as f64 * dt;
            let moving = (t - 0.007).max(0.0);
            match pulse.observe(&state(t, 0.5 * 0.25 * moving * moving)) {
                Step::Done(m) => return assert!((m - 0.2).abs() < 0.01, "{m}"),
                Step::Blocked { .. } => panic!("timed out"),
                Step::Running => {}
            }
        }
        panic!("never done");
    }
}
