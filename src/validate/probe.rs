//! The application side of the experiment: what a client of the daemon would render, tick by tick,
//! from the state it is sent. It carries the handle to each contact point, lowers it onto a
//! horizontal surface, waits for the steady state and records where the handle rests (the paper's
//! reading, from above); then drops the surface by a little and raises it back into place, so the
//! handle rises to its rest and is read again from below; then lifts it off and lowers it again
//! (so friction is sampled afresh at every repetition). Friction stops a handle short of its
//! equilibrium on the side it comes from, so the two readings bracket it. With a dither (the
//! default), each reading is instead the handle's mean position under a vibration well above its
//! natural frequency and stronger than the friction: its slow motion finds the equilibrium as if
//! there were no friction, and the mean resolves it below one encoder count ([`Dithered`]).
//!
//! The force it asks for, with n the unit "up" (opposite to gravity, docs/validation.md §2),
//! N = n nᵀ and T = I − N:
//!
//! F = k_h T (R − X) − c_h T V + w [k_h N (R − X) − c_h N V] + s n max(0, k d − c V·n)
//!
//! (the last term for d > 0 only)
//!
//! R is a reference point, w ∈ [0, 1] weighs the vertical part of the hold, s ∈ [0, 1] the
//! surface, d = (P − X)·n − δ the depth below the surface, which lies at the contact point P
//! dropped by δ (0 but while the reading from below is prepared). The across-surface part of the hold
//! (the horizontal hold) is always on; the vertical part is faded out before the steady state, so
//! the surface alone then carries the weight, and faded in again to lift the handle off.

use nalgebra::Vector3;

use crate::config::Config;
use crate::control::{minimum_jerk, DeviceState};
use crate::estimate::steady::SteadyState;

/// The dither's frequencies across the surface, relative to the one along its normal: the
/// highest is [`DITHER_ACROSS`].
const DITHER_ACROSS_1: f64 = 1.23;
pub const DITHER_ACROSS: f64 = 1.51;
/// Damping of the hold per unit of its stiffness, s (c_h = k_h · this).
const HOLD_DAMPING_TIME: f64 = 0.01;
/// Fading the vertical hold out before a steady state (load onto the surface), s.
const RELEASE_TIME: f64 = 0.1;
/// Fading the vertical hold in before lifting, and the surface out before a transit, s.
const GRIP_TIME: f64 = 0.05;
/// Lowering the reference from the lift height onto the surface, s (minimum jerk).
const LOWER_TIME: f64 = 0.15;
/// Dropping the surface below the contact point, and raising it back, s each (minimum jerk).
const DROP_TIME: f64 = 0.15;
/// Raising it back to the lift height, s (minimum jerk).
const RAISE_TIME: f64 = 0.1;
/// Transits between contact points: at least this long, s ...
const TRANSIT_MIN_TIME: f64 = 0.2;
/// ... and at this mean speed, m/s (minimum jerk, so the peak is 1.875 times this).
const TRANSIT_SPEED: f64 = 0.15;

/// The experiment's parameters, SI.
#[derive(Clone, Debug, PartialEq)]
pub struct ProbeParams {
    /// Surface stiffness k, N/m.
    pub stiffness: f64,
    /// Surface damping c, N·s/m.
    pub surface_damping: f64,
    /// Hold stiffness k_h, N/m.
    pub hold_stiffness: f64,
    /// Lift height above the surface, m.
    pub lift: f64,
    /// How far the surface drops before it rises back into place for the reading from below, m.
    pub drop: f64,
    /// The dither each reading is taken under: amplitude per direction, N (0: none, the paper's
    /// steady state) ...
    pub dither: f64,
    /// ... frequency along the normal, Hz ...
    pub dither_frequency: f64,
    /// ... and duration (three windows: equilibrium, reading, fade), s.
    pub dither_time: f64,
    /// Steady state: samples per window.
    pub steady_samples: usize,
    /// Steady state: sphere radius, m.
    pub steady_radius: f64,
    /// A repetition with no steady state after this long is recorded unsettled, s.
    pub settle_timeout: f64,
    /// Largest force per axis an application may ask for, N.
    pub max_force: f64,
}

impl ProbeParams {
    /// The parameters `config` gives (`validation.*`, `safety.max_force_n`) for a surface of
    /// stiffness `stiffness`, N/m.
    pub fn configured(config: &Config, stiffness: f64) -> Self {
        let v = &config.validation;
        Self {
            stiffness,
            surface_damping: v.surface_damping_n_s_per_m,
            hold_stiffness: v.hold_stiffness(),
            lift: v.lift(),
            drop: v.drop(),
            dither: v.dither_n,
            dither_frequency: v.dither_hz,
            dither_time: v.dither_s,
            steady_samples: v.n_s,
            steady_radius: v.eps_s(),
            settle_timeout: v.settle_timeout_s,
            max_force: config.safety.max_force_n,
        }
    }
}

/// Where and how often: the contact points (in their numbered order), the order they are visited
/// in, the surface normal, and the number of runs (one per compensation mode) and repetitions.
#[derive(Clone, Debug, PartialEq)]
pub struct ContactPlan {
    /// Contact points P_n, m; index n − 1 for the point numbered n.
    pub points: Vec<Vector3<f64>>,
    /// Indices into `points`, in visiting order.
    pub order: Vec<usize>,
    /// Unit "up", the surface normal (v_G).
    pub normal: Vector3<f64>,
    pub runs: usize,
    pub repetitions: usize,
}

impl ContactPlan {
    /// The 27 points centre + spacing·(i, j, k), i, j, k ∈ {−1, 0, 1}, numbered with x fastest
    /// (n = 1 + (i+1) + 3(j+1) + 9(k+1)), visited along a serpentine path.
    pub fn paper(
        centre: Vector3<f64>,
        spacing: f64,
        normal: Vector3<f64>,
        runs: usize,
        repetitions: usize,
    ) -> Self {
        let mut points = Vec::with_capacity(27);
        for k in -1..=1 {
            for j in -1..=1 {
                for i in -1..=1 {
                    points.push(centre + Vector3::new(i as f64, j as f64, k as f64) * spacing);
                }
            }
        }
        let mut order = Vec::with_capacity(27);
        for k in 0..3 {
            for jj in 0..3 {
                // Reverse every other row and every other layer: neighbours follow each other.
                let j = if k % 2 == 0 { jj } else { 2 - jj };
                for ii in 0..3 {
                    let i = if (jj + k) % 2 == 0 { ii } else { 2 - ii };
                    order.push(i + 3 * j + 9 * k);
                }
            }
        }
        Self {
            points,
            order,
            normal: normal.normalize(),
            runs,
            repetitions,
        }
    }

    /// Repetitions in the whole experiment.
    pub fn total(&self) -> usize {
        self.runs * self.points.len() * self.repetitions
    }

    /// Readings in the whole experiment: two per repetition.
    pub fn readings(&self) -> usize {
        2 * self.total()
    }
}

/// Which side the handle came to rest from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Reading {
    /// Sinking into the surface from above: the paper's procedure.
    Above,
    /// Pushed up by the surface as it rises back into place.
    Below,
    /// The middle of the two rests of one repetition: hgcd's procedure.
    TwoSided,
}

impl Reading {
    pub const ALL: [Reading; 3] = [Reading::Above, Reading::Below, Reading::TwoSided];

    pub fn name(self) -> &'static str {
        match self {
            Reading::Above => "above",
            Reading::Below => "below",
            Reading::TwoSided => "two-sided",
        }
    }
}

/// One reading: where the handle came to rest on the surface.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Rest {
    /// Run (compensation mode), in plan order.
    pub run: usize,
    /// Index of the contact point in [`ContactPlan::points`].
    pub point: usize,
    pub repetition: usize,
    /// [`Reading::Above`] or [`Reading::Below`].
    pub reading: Reading,
    /// Mean position over the steady window, or under the dither over its reading window, m.
    pub position: Vector3<f64>,
    /// False when no steady state came within the timeout (`position` is then the newest
    /// window's mean, or the last sample), or under the dither when the reading window's two
    /// halves disagree by more than the steady-state radius.
    pub settled: bool,
    /// Time from the end of the release (from above) or of the surface's rise (from below) to
    /// the steady state, or with a dither to the end of its reading window, s.
    pub settle_time: f64,
}

/// What the application is doing.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Phase {
    /// Nothing yet: the first state sets the reference where the handle is.
    Start,
    /// Carrying the handle at lift height to above the next contact point; the surface it leaves
    /// fades out.
    Transit {
        from: Vector3<f64>,
        to: Vector3<f64>,
        duration: f64,
        surface_from: f64,
    },
    /// Lowering the reference onto the surface.
    Lower,
    /// Fading the vertical hold out.
    Release,
    /// Shaking the handle free of static friction, reading its rest as the mean position under
    /// the vibration (see [`Dithered`]), and fading the vibration out.
    Dither(Reading, Dithered),
    /// Waiting for the steady state, approached from one side.
    Settle(Reading),
    /// Dropping the surface by [`ProbeParams::drop`].
    Drop,
    /// Raising it back into place.
    Raise,
    /// Fading the vertical hold in, then raising the reference to lift height.
    Lift,
    /// All repetitions done: holding the handle at lift height.
    Finished,
}

/// The dither's reading: the handle vibrates about its equilibrium, across the encoders'
/// counts, so the mean of its position over a window resolves the rest below one count (a
/// resting handle reads whole counts: on the simulated delta 38 µm, 13 % of the ideal penalty).
/// The dither's time is three windows: the handle finds its equilibrium in the first, the
/// second is read, the vibration fades out over the third. The reading counts as settled when
/// the window's two halves agree within the steady-state radius (a handle still sliding does
/// not).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Dithered {
    /// The position summed over each half of the reading window, m, and their samples.
    sum: [Vector3<f64>; 2],
    samples: [usize; 2],
    /// The reading has been taken.
    read: bool,
}

impl Dithered {
    const START: Self = Self {
        sum: [Vector3::new(0.0, 0.0, 0.0); 2],
        samples: [0; 2],
        read: false,
    };
}

/// Which repetition of which point of which run.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Cursor {
    run: usize,
    /// Index into [`ContactPlan::order`].
    visit: usize,
    repetition: usize,
}

/// One tick's answer.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ProbeStep {
    /// The force offset to send, N.
    pub force: Vector3<f64>,
    /// A repetition ended at this state.
    pub rest: Option<Rest>,
}

/// The experiment as an application renders it: state in, force offset out.
#[derive(Clone, Debug)]
pub struct Probe {
    plan: ContactPlan,
    params: ProbeParams,
    phase: Phase,
    /// When the phase began, device time, s.
    since: f64,
    cursor: Cursor,
    reference: Vector3<f64>,
    /// How far the surface is below the contact point, m.
    surface_drop: f64,
    /// The paper's steady state, read as for calibration (docs/calibration.md).
    steady: SteadyState,
    /// The normal and two unit directions across the surface, for the dither.
    basis: [Vector3<f64>; 3],
}

impl Probe {
    pub fn new(plan: ContactPlan, params: ProbeParams) -> Self {
        let steady = SteadyState::new(params.steady_samples, params.steady_radius);
        let normal = plan.normal;
        let (across_1, across_2) = crate::fit::across(&normal);
        Self {
            plan,
            params,
            phase: Phase::Start,
            since: 0.0,
            cursor: Cursor {
                run: 0,
                visit: 0,
                repetition: 0,
            },
            reference: Vector3::zeros(),
            surface_drop: 0.0,
            steady,
            basis: [normal, across_1, across_2],
        }
    }

    pub fn plan(&self) -> &ContactPlan {
        &self.plan
    }

    /// The run (compensation mode) under way: it changes when the transit to the first point of
    /// the next run begins.
    pub fn run(&self) -> usize {
        self.cursor.run
    }

    /// Every repetition is done.
    pub fn finished(&self) -> bool {
        self.phase == Phase::Finished
    }

    fn point(&self) -> Vector3<f64> {
        self.plan.points[self.plan.order[self.cursor.visit]]
    }

    fn above(&self, p: &Vector3<f64>) -> Vector3<f64> {
        p + self.plan.normal * self.params.lift
    }

    fn enter(&mut self, phase: Phase, t: f64) {
        self.phase = phase;
        self.since = t;
    }

    /// Start the transit to the point the cursor names, from the reference.
    fn transit(&mut self, t: f64, surface_from: f64) {
        let to = self.above(&self.point());
        let distance = (to - self.reference).norm();
        let duration = (distance / TRANSIT_SPEED).max(TRANSIT_MIN_TIME);
        let from = self.reference;
        self.enter(
            Phase::Transit {
                from,
                to,
                duration,
                surface_from,
            },
            t,
        );
    }

    /// The state `s` as the application receives it; the force offset it answers with.
    pub fn step(&mut self, s: &DeviceState) -> ProbeStep {
        let t = s.time;
        let mut rest = None;
        // (vertical hold weight w, surface weight)
        let (w, surface) = match self.phase {
            Phase::Start => {
                self.reference = s.position;
                self.transit(t, 0.0);
                (1.0, 0.0)
            }
            Phase::Transit {
                from,
                to,
                duration,
                surface_from,
            } => {
                let u = t - self.since;
                self.reference = from + (to - from) * minimum_jerk(u / duration).0;
                let surface = surface_from * (1.0 - u / GRIP_TIME).max(0.0);
                if u >= duration {
                    self.enter(Phase::Lower, t);
                }
                (1.0, surface)
            }
            Phase::Lower => {
                let u = t - self.since;
                let p = self.point();
                self.reference = p + self.plan.normal
                    * (self.params.lift * (1.0 - minimum_jerk(u / LOWER_TIME).0));
                if u >= LOWER_TIME {
                    self.enter(Phase::Release, t);
                }
                (1.0, 1.0)
            }
            Phase::Release => {
                let w = 1.0 - (t - self.since) / RELEASE_TIME;
                if w <= 0.0 {
                    self.settle(Reading::Above, t);
                }
                (w.max(0.0), 1.0)
            }
            Phase::Dither(reading, mut dithered) => {
                let u = t - self.since;
                let window = self.window();
                // The first window lets the handle find its equilibrium; the second is read, in
                // two halves; over the third the vibration fades out.
                if (window..2.0 * window).contains(&u) {
                    let half = usize::from(u >= 1.5 * window);
                    dithered.sum[half] += s.position;
                    dithered.samples[half] += 1;
                } else if u >= 2.0 * window && !dithered.read {
                    let [a, b] = [0, 1].map(|h| dithered.sum[h] / dithered.samples[h] as f64);
                    // Converged: both halves sampled, their means within the steady-state
                    // radius of each other (a handle still sliding is not).
                    let settled = dithered.samples.iter().all(|&n| n > 0)
                        && (a - b).norm() <= self.params.steady_radius;
                    let samples = dithered.samples[0] + dithered.samples[1];
                    let position = if samples > 0 {
                        (dithered.sum[0] + dithered.sum[1]) / samples as f64
                    } else {
                        s.position
                    };
                    rest = Some(self.rest(reading, position, settled, u));
                    dithered.read = true;
                }
                if u >= 3.0 * window {
                    self.after(reading, t);
                } else {
                    self.phase = Phase::Dither(reading, dithered);
                }
                // Faded in over a quarter of the first window (no kick at the handle's own
                // frequency), out over the third.
                let envelope = (u / (0.25 * window))
                    .min(1.0)
                    .min((3.0 * window - u) / window)
                    .clamp(0.0, 1.0);
                return ProbeStep {
                    force: self.force(s, 0.0, 1.0, self.dither(u, self.params.dither * envelope)),
                    rest,
                };
            }
            Phase::Drop => {
                let u = (t - self.since) / DROP_TIME;
                self.surface_drop = self.params.drop * minimum_jerk(u).0;
                if u >= 1.0 {
                    self.enter(Phase::Raise, t);
                }
                (0.0, 1.0)
            }
            Phase::Raise => {
                let u = (t - self.since) / DROP_TIME;
                self.surface_drop = self.params.drop * (1.0 - minimum_jerk(u).0);
                if u >= 1.0 {
                    self.settle(Reading::Below, t);
                }
                (0.0, 1.0)
            }
            Phase::Settle(reading) => {
                let waited = t - self.since;
                let found = self.steady.push(&s.position);
                if found.is_some() || waited >= self.params.settle_timeout {
                    let position = found
                        .or_else(|| self.steady.last_mean())
                        .unwrap_or(s.position);
                    rest = Some(self.rest(reading, position, found.is_some(), waited));
                    self.after(reading, t);
                }
                (0.0, 1.0)
            }
            Phase::Lift => {
                let u = t - self.since;
                let p = self.point();
                let raise = ((u - GRIP_TIME) / RAISE_TIME).max(0.0);
                self.reference = p + self.plan.normal * (self.params.lift * minimum_jerk(raise).0);
                if raise >= 1.0 {
                    self.next(t);
                }
                ((u / GRIP_TIME).min(1.0), 1.0)
            }
            Phase::Finished => (1.0, 0.0),
        };
        ProbeStep {
            force: self.force(s, w, surface, Vector3::zeros()),
            rest,
        }
    }

    /// Read the rest from the side `reading` names: under the dither, or without one at the
    /// steady state.
    fn settle(&mut self, reading: Reading, t: f64) {
        if self.params.dither > 0.0 {
            self.enter(Phase::Dither(reading, Dithered::START), t);
        } else {
            self.steady.reset();
            self.enter(Phase::Settle(reading), t);
        }
    }

    /// A window of the dither: a third of its time.
    fn window(&self) -> f64 {
        self.params.dither_time / 3.0
    }

    /// The reading `reading` of the repetition under way: at `position`, settled or not, after
    /// `waited` seconds.
    fn rest(&self, reading: Reading, position: Vector3<f64>, settled: bool, waited: f64) -> Rest {
        Rest {
            run: self.cursor.run,
            point: self.plan.order[self.cursor.visit],
            repetition: self.cursor.repetition,
            reading,
            position,
            settled,
            settle_time: waited,
        }
    }

    /// After the reading `reading`: drop the surface for the reading from below, or lift off.
    fn after(&mut self, reading: Reading, t: f64) {
        let next = match reading {
            Reading::Above => Phase::Drop,
            _ => Phase::Lift,
        };
        self.enter(next, t);
    }

    /// The dither's force `u` seconds into it at `amplitude`, N: along the normal at its
    /// frequency, across the surface at 1.23 and 1.51 times that (the three come back into
    /// step only after 100 periods, longer than a reading window).
    fn dither(&self, u: f64, amplitude: f64) -> Vector3<f64> {
        let p = &self.params;
        let phase = std::f64::consts::TAU * p.dither_frequency * u;
        let [normal, across_1, across_2] = &self.basis;
        (normal * phase.sin()
            + across_1 * (DITHER_ACROSS_1 * phase).sin()
            + across_2 * (DITHER_ACROSS * phase).sin())
            * amplitude
    }

    /// After a lift: the next repetition, point or run, or the end.
    fn next(&mut self, t: f64) {
        let c = &mut self.cursor;
        c.repetition += 1;
        if c.repetition < self.plan.repetitions {
            self.enter(Phase::Lower, t);
            return;
        }
        c.repetition = 0;
        c.visit += 1;
        if c.visit == self.plan.order.len() {
            c.visit = 0;
            c.run += 1;
            if c.run == self.plan.runs {
                // Stay on the last point's lift height; the run counter stays in range.
                c.run -= 1;
                c.visit = self.plan.order.len() - 1;
                self.enter(Phase::Finished, t);
                return;
            }
        }
        self.transit(t, 1.0);
    }

    /// The force for state `s` with the vertical hold weighed by `w`, the surface by `surface`,
    /// and `dither` added.
    fn force(&self, s: &DeviceState, w: f64, surface: f64, dither: Vector3<f64>) -> Vector3<f64> {
        let n = self.plan.normal;
        let k_h = self.params.hold_stiffness;
        let c_h = k_h * HOLD_DAMPING_TIME;
        let e = self.reference - s.position;
        let (e_n, v_n) = (e.dot(&n), s.velocity.dot(&n));
        let e_t = e - n * e_n;
        let v_t = s.velocity - n * v_n;
        let mut f = e_t * k_h - v_t * c_h + n * (w * (k_h * e_n - c_h * v_n));
        if surface > 0.0 {
            let depth = (self.point() - s.position).dot(&n) - self.surface_drop;
            if depth > 0.0 {
                let push = self.params.stiffness * depth - self.params.surface_damping * v_n;
                f += n * (surface * push.max(0.0));
            }
        }
        let limit = self.params.max_force;
        (f + dither).map(|c| c.clamp(-limit, limit))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_paper_points_are_numbered_x_fastest_and_visited_by_neighbours() {
        let plan = ContactPlan::paper(Vector3::zeros(), 0.03, Vector3::z(), 1, 1);
        assert_eq!(plan.points[0], Vector3::new(-0.03, -0.03, -0.03));
        assert_eq!(plan.points[1], Vector3::new(0.0, -0.03, -0.03));
        assert_eq!(plan.points[26], Vector3::new(0.03, 0.03, 0.03));
        let mut seen = plan.order.clone();
        seen.sort_unstable();
        assert_eq!(seen, (0..27).collect::<Vec<_>>());
        for pair in plan.order.windows(2) {
            let step = (plan.points[pair[1]] - plan.points[pair[0]]).norm();
            assert!((step - 0.03).abs() < 1e-12, "{pair:?}");
        }
    }

    #[test]
    fn steady_state_needs_two_agreeing_windows() {
        let p = |x: f64| Vector3::new(x, 0.0, 0.0);
        let mut d = SteadyState::new(3, 1e-4);
        // Creeping by 10 µm a sample (30 µm per window, ε/10 = 10 µm): never steady.
        for k in 0..30 {
            assert!(d.push(&p(k as f64 * 1e-5)).is_none());
        }
        let mut d = SteadyState::new(3, 1e-4);
        let found = (0..6).filter_map(|_| d.push(&p(1e-3))).last();
        assert_eq!(found, Some(p(1e-3)));
    }

    fn state(t: f64, x: Vector3<f64>, v: Vector3<f64>) -> DeviceState {
        DeviceState {
            time: t,
            host_time: t,
            position: x,
            velocity: v,
            status: Default::default(),
            tick: 0,
        }
    }

    /// The defaults, on a surface of 1 N/mm.
    fn params() -> ProbeParams {
        ProbeParams::configured(&Config::default(), 1000.0)
    }

    /// A point mass m under gravity g along −z, pushed by the probe's force one tick late (as a
    /// client's offset is applied), integrated at 10 kHz: the paper's procedure, without a
    /// dither. (A dither on a handle this light, the probe alone, would move it at 3 cm/s, and
    /// the surface's damping, which can only push, would rectify it; docs/validation.md §2.)
    #[test]
    fn a_probe_mass_on_the_surface_rests_at_its_weight_over_the_stiffness() {
        let (m, g, dt) = (0.03, 9.81, 1e-3);
        let plan = ContactPlan::paper(Vector3::zeros(), 0.03, Vector3::z(), 1, 2);
        let params = ProbeParams {
            dither: 0.0,
            ..params()
        };
        let mut probe = Probe::new(plan, params);
        let (mut x, mut v) = (Vector3::new(0.01, 0.0, 0.0), Vector3::zeros());
        let mut applied = Vector3::zeros();
        let mut rests = Vec::new();
        let mut t = 0.0;
        while !probe.finished() {
            let step = probe.step(&state(t, x, v));
            for _ in 0..10 {
                let a = applied / m - Vector3::z() * g - v * (1.0 / m);
                v += a * dt / 10.0;
                x += v * dt / 10.0;
            }
            applied = step.force;
            rests.extend(step.rest);
            t += dt;
            assert!(t < 200.0, "the experiment does not end");
        }
        assert_eq!(rests.len(), 108);
        let ideal = m * g / 1000.0;
        for r in &rests {
            let p = probe.plan().points[r.point];
            let penalty = (p - r.position).norm();
            assert!(r.settled);
            assert!((penalty / ideal - 1.0).abs() < 0.01, "{r:?}: {penalty}");
        }
    }

    /// Where a handle of 100 g (its own weight compensated) carrying the 30 g probe rests on the
    /// surface under 0.1 N of Coulomb friction, each reading's deviation from the ideal penalty
    /// m_p g / k. Integrated at 10 kHz; friction holds the handle while the force on it stays
    /// within 0.1 N and opposes its motion otherwise.
    fn deviations_under_friction(params: ProbeParams) -> Vec<(Reading, f64)> {
        let (m, m_p, g, f_c, dt) = (0.1, 0.03, 9.81, 0.1, 1e-4);
        let plan = ContactPlan::paper(Vector3::zeros(), 0.03, Vector3::z(), 1, 2);
        let mut probe = Probe::new(plan, params);
        let (mut x, mut v) = (Vector3::new(0.01, 0.0, 0.0), Vector3::<f64>::zeros());
        let (mut applied, mut t, mut rests) = (Vector3::zeros(), 0.0, Vec::new());
        while !probe.finished() {
            let step = probe.step(&state(t, x, v));
            for _ in 0..10 {
                let force = applied - Vector3::z() * (m_p * g);
                if v == Vector3::zeros() && force.norm() <= f_c {
                    continue;
                }
                let sliding = if v == Vector3::zeros() { force } else { v };
                let next = v + (force - sliding.normalize() * f_c) * (dt / m);
                v = if next.dot(&v) < 0.0 {
                    Vector3::zeros()
                } else {
                    next
                };
                x += v * dt;
            }
            applied = step.force;
            rests.extend(step.rest);
            t += 1e-3;
            assert!(t < 200.0, "the experiment does not end");
        }
        let ideal = m_p * g / 1000.0;
        rests
            .iter()
            .map(|r| {
                assert!(r.settled, "{r:?}");
                let penalty = (probe.plan().points[r.point] - r.position).norm();
                (r.reading, penalty / ideal - 1.0)
            })
            .collect()
    }

    /// Friction stops the handle a band's width short of (from above) or beyond (from below) its
    /// equilibrium, 0.1 N / k = 34 % of the ideal penalty here; the dither lets it reach the
    /// equilibrium from either side.
    #[test]
    fn the_dither_frees_each_reading_from_the_friction_band() {
        let plain = ProbeParams {
            dither: 0.0,
            ..params()
        };
        for (reading, deviation) in deviations_under_friction(plain) {
            match reading {
                Reading::Above => assert!(deviation < -0.2, "{reading:?}: {deviation}"),
                _ => assert!(deviation > 0.2, "{reading:?}: {deviation}"),
            }
        }
        for (reading, deviation) in deviations_under_friction(params()) {
            assert!(deviation.abs() < 0.03, "{reading:?}: {deviation}");
        }
    }
}
