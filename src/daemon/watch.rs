//! Noticed in use (docs/calibration.md §2.3): is the gravity model still right, read from the
//! states the servo thread publishes, on the hub's thread.
//!
//! While the force sent is the model's alone (no application offset, no calibration), a handle
//! the model holds exactly does not accelerate, apart from friction. Under a payload the model
//! does not know, a released handle keeps sinking: (M + m_p) a = −m_p g v_G − c v − f sgn(v),
//! with M the moving mass and f the sliding friction the calibration measured (its
//! `[calibration]` record) and c a viscous damping it did not (on a linkage, the velocity
//! product of its swing instead). The mean velocities of windows of [`WINDOW`] give a from one
//! window to the next; [`WINDOWS`] such steps in a row that one missed force and one speed's
//! force explain within [`AGREEMENT`] give the force the model misses (the payload's weight
//! along v_G, something else across it), if the handle really moves that way: sliding,
//! speeding up along its motion and covering the way its velocities say (velocity noise at
//! rest does none of these). A hand on the handle, a stop, a bump do not move it that way for
//! long.
//!
//! While an application renders a force (its own spring, say) and the handle rests, the
//! application's offset holds what the model misses, give or take the friction: at rest
//! F_missed = offset + f_s with |f_s| ≤ f along each axis. A hand on the handle holds it still
//! too, but a hand does not push with the same force wherever the handle is: only
//! [`HELD_RESTS`] rests at places [`HELD_APART`] apart whose offsets agree within the friction
//! (and [`AGREEMENT`] of the offset) read as a missed force, and only one beyond what friction
//! could hold.
//!
//! A missed force is read through the model ([`Noticed::of`]): the payload and the turn of
//! gravity that make the model's force the one needed. On a device with an arm model (a
//! linkage, whose inertia couples the axes) a released handle shows only what acts along v_G.

use nalgebra::{Matrix3, Rotation3, Vector3};

use crate::app::protocol::StaleEvidence;
use crate::control::compensation::GravityModel;
use crate::fit::across;
use crate::grid::GridFile;
use crate::mailbox::PublishedState;
use crate::protocol::Status;

/// Length of one window of states, s.
pub const WINDOW: f64 = 0.04;
/// Steps from one window to the next, in a row, that one missed force and one speed's force
/// must explain (read after the motion's first window: [`WINDOWS`] + 2 windows of motion).
pub const WINDOWS: usize = 4;
/// How far each window may be from that explanation, as a share of the force missed.
pub const AGREEMENT: f64 = 0.1;
/// The smallest force missed that is reported, N (about half a gram's weight), and as a share
/// of the model's force there: a model within its calibration's accuracy (0.5 % at the worst
/// vertex, docs/calibration.md §7.1) between its vertices, read through a moving mass and a
/// damping estimated on the way, must not raise an alarm.
pub const MIN_FORCE: f64 = 0.005;
pub const MIN_SHARE: f64 = 0.05;
/// A velocity component below this is not moving against friction, m/s.
const MOVING: f64 = 0.001;
/// A rest under an application's force: the handle within [`HELD_RADIUS`] of where the rest
/// began for this long, s, the offset steady within the friction (or [`MIN_FORCE`]) all along.
pub const HELD_TIME: f64 = 0.2;
/// How far a handle at rest may wander, m: slower than [`MOVING`] over [`HELD_TIME`], and a few
/// encoder counts of the coarsest simulated device (65 µm), whose readings flicker at rest
/// (its velocity estimate does not always stay under [`MOVING`]).
pub const HELD_RADIUS: f64 = 0.2e-3;
/// Rests whose offsets must agree, at places at least this far apart, m (not one stop pushed
/// against again and again).
pub const HELD_RESTS: usize = 3;
pub const HELD_APART: f64 = 0.005;
/// States further apart than this many of the shortest step seen break a window (dropped
/// samples, a pause).
const GAP_STEPS: f64 = 3.0;
/// Gauss–Newton steps reading a missed force as a payload and a tilt.
const TURNS: usize = 6;
/// A tilt (or payload) changing the model's force by less than this per degree (per gram), N,
/// is not read from the force there.
const UNREADABLE: f64 = 1e-4;

/// What a watch noticed: the force the model misses, read as a payload and what is left.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Noticed {
    /// The payload that, with [`Noticed::tilt`], makes the model's force the one needed, kg.
    pub payload_kg: f64,
    /// The missed force read across v_G, N (none from a linkage's released handle; at rest,
    /// only what is beyond the friction).
    pub sideways_n: f64,
    /// Gravity turned (axis times angle, rad, across v_G): a lattice's field turned, an arm
    /// model's gravity turned ([`GravityModel::changed`]).
    pub tilt: Vector3<f64>,
    /// Device time of the last state read, s.
    pub time: f64,
    /// What showed it.
    pub evidence: StaleEvidence,
}

impl Noticed {
    /// What `missed` (N) at `at` (m) says of `model`: the payload and the tilt (gravity turned
    /// across v_G) that make the model's force there its force plus `missed`
    /// ([`GravityModel::changed`]). On a uniform field the payload's weight is the missed force
    /// along v_G and the tilt turns the field; on a linkage the arm's own force turns with the
    /// arm, so they are read through the model, by Gauss–Newton from no change. A tilt that
    /// hardly changes the force there is not read (left at none), nor any without `read_tilt`
    /// (what was missed across v_G is not known). None when the reading is not finite.
    fn of(
        missed: Vector3<f64>,
        at: &Vector3<f64>,
        model: &GravityModel,
        read_tilt: bool,
        time: f64,
        evidence: StaleEvidence,
    ) -> Option<Self> {
        let up = model.gravity_up();
        let (e1, e2) = across(&up);
        // The change: a turn of gravity across v_G (rad about e1, e2) and a payload (kg).
        let force = |c: &Vector3<f64>| {
            model
                .changed(&Rotation3::new(e1 * c.x + e2 * c.y), c.z)
                .force(at)
        };
        let target = model.force(at) + missed;
        // Steps of 0.1° and 0.1 g: the columns in N per degree and per gram.
        let steps = Vector3::new(1f64.to_radians(), 1f64.to_radians(), 1e-3) * 0.1;
        let mut change = Vector3::zeros();
        for _ in 0..TURNS {
            let here = force(&change);
            if (target - here).norm() < 1e-9 {
                break;
            }
            let columns: [Vector3<f64>; 3] = std::array::from_fn(|n| {
                if n < 2 && !read_tilt {
                    return Vector3::zeros();
                }
                let mut c = change;
                c[n] += steps[n];
                (force(&c) - here) * 10.0
            });
            let jacobian = Matrix3::from_columns(&columns);
            let Ok(step) = jacobian.svd(true, true).solve(&(target - here), UNREADABLE) else {
                break;
            };
            change += step.component_mul(&steps) * 10.0;
        }
        let noticed = Self {
            payload_kg: change.z,
            sideways_n: (missed - up * missed.dot(&up)).norm(),
            tilt: e1 * change.x + e2 * change.y,
            time,
            evidence,
        };
        (noticed.payload_kg.is_finite()
            && noticed.sideways_n.is_finite()
            && noticed.tilt.iter().all(|t| t.is_finite()))
        .then_some(noticed)
    }
}

/// One stretch of rest under an application's offset: sums of the offset and the position,
/// the offset's extremes.
#[derive(Clone, Copy, Debug)]
struct Held {
    start: f64,
    /// Where the rest began, m.
    at: Vector3<f64>,
    last: f64,
    n: f64,
    offset: Vector3<f64>,
    position: Vector3<f64>,
    low: Vector3<f64>,
    high: Vector3<f64>,
    /// Σ of the model's force, N.
    force: Vector3<f64>,
}

/// A rest read: where, and the application's mean offset there, N.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Rest {
    position: Vector3<f64>,
    offset: Vector3<f64>,
}

/// One window read: its mean time (s), velocity (m/s) and position (m).
#[derive(Clone, Copy, Debug)]
struct Span {
    time: f64,
    velocity: Vector3<f64>,
    position: Vector3<f64>,
}

/// The running fit of one window: sums of t, t², v and t v (t from the window's start).
#[derive(Clone, Copy, Debug, Default)]
struct Window {
    start: f64,
    last: f64,
    n: f64,
    t: f64,
    tt: f64,
    v: Vector3<f64>,
    tv: Vector3<f64>,
    /// Σ F of the forces sent (the model's), N, and Σ X, m.
    force: Vector3<f64>,
    position: Vector3<f64>,
}

/// The watch over one gravity model.
#[derive(Clone, Debug)]
pub struct ModelWatch {
    /// The model watched (its v_G, what a payload or a tilt would make its force).
    model: GravityModel,
    /// The grid has an arm model, whatever the compensation mode: a linkage, whose inertia
    /// couples the axes.
    coupled: bool,
    /// Moving mass along each axis, kg, and friction along each, N (the calibration's): what
    /// holds a handle at rest (half its stick band) and what a sliding handle meets (the survey
    /// strokes', usually 5–30 % less; the band's in files without it).
    moving_mass: Vector3<f64>,
    friction: Vector3<f64>,
    sliding_friction: Vector3<f64>,
    window: Option<Window>,
    /// The last windows in a row, oldest first (at most [`WINDOWS`] + 1: [`WINDOWS`] steps).
    recent: Vec<Span>,
    /// The mean force the model gave in the last window (or rest), N, and where, m.
    model_force: Vector3<f64>,
    at: Vector3<f64>,
    /// Windows in a row whose acceleration alone shows a force of [`MIN_FORCE`].
    moving: usize,
    step: f64,
    noticed: bool,
    /// The rest under an application's offset being read, and the last rests read, at places
    /// [`HELD_APART`] apart (a rest near one kept replaces it).
    held: Option<Held>,
    rests: Vec<Rest>,
}

impl ModelWatch {
    /// A watch over `model`, built from `file`: the moving mass and friction its calibration
    /// recorded (without them, the apparent mass at its centre and no friction).
    pub fn new(file: &GridFile, model: &GravityModel) -> Self {
        let grid = &file.grid;
        let record = file.calibration.as_ref();
        let centre = (grid.origin + grid.far_corner()) / 2.0;
        let mass = grid.mass_at(&centre).abs().max(0.001);
        let is_friction = |f: &Vector3<f64>| f.iter().all(|f| f.is_finite() && *f >= 0.0);
        let friction = record
            .and_then(|c| c.friction_n)
            .map(Vector3::from)
            .filter(is_friction)
            .unwrap_or_else(Vector3::zeros);
        Self {
            moving_mass: record
                .and_then(|c| c.inertia_kg)
                .map_or(Vector3::repeat(mass), Vector3::from),
            friction,
            sliding_friction: record
                .and_then(|c| c.sliding_friction_n)
                .map(Vector3::from)
                .filter(is_friction)
                .unwrap_or(friction),
            model: model.clone(),
            coupled: file.arm.is_some(),
            window: None,
            recent: Vec::with_capacity(WINDOWS + 2),
            moving: 0,
            model_force: Vector3::zeros(),
            at: Vector3::zeros(),
            step: f64::INFINITY,
            noticed: false,
            held: None,
            rests: Vec::with_capacity(HELD_RESTS),
        }
    }

    /// Read one published state; what it noticed, once per watch.
    pub fn observe(&mut self, p: &PublishedState) -> Option<Noticed> {
        let s = &p.state;
        let disturbed = s.status.bits()
            & (Status::FAULT | Status::FORCE_SATURATED | Status::DEVICE_WATCHDOG)
            != 0;
        let finite = s.time.is_finite()
            && s.velocity.iter().all(|v| v.is_finite())
            && p.force.iter().all(|f| f.is_finite());
        let readable = !self.noticed && !disturbed && finite;
        // Under an application's force (the model compensating beside it), rests are read;
        // anything else (a calibration, a hold, no model) breaks a rest.
        let offset = p.force - p.gravity;
        let applied =
            !p.gravity_only && p.gravity != Vector3::zeros() && offset != Vector3::zeros();
        if !(readable && applied) {
            self.held = None;
        } else if let Some(noticed) = self.held_still(p, offset) {
            return Some(noticed);
        }
        if !(readable && p.gravity_only) {
            self.window = None;
            self.recent.clear();
            self.moving = 0;
            return None;
        }
        if let Some(w) = &self.window {
            let step = s.time - w.last;
            if step > 0.0 {
                self.step = self.step.min(step);
            }
            if step <= 0.0 || step > GAP_STEPS * self.step {
                self.window = None;
                self.recent.clear();
                self.moving = 0;
            }
        }
        let w = self.window.get_or_insert(Window {
            start: s.time,
            ..Window::default()
        });
        let t = s.time - w.start;
        w.last = s.time;
        w.n += 1.0;
        w.t += t;
        w.tt += t * t;
        w.v += s.velocity;
        w.tv += s.velocity * t;
        w.force += p.force;
        w.position += s.position;
        if t < WINDOW {
            return None;
        }
        let w = self.window.take().expect("a window");
        let spread = w.n * w.tt - w.t * w.t;
        if spread <= 0.0 {
            return None;
        }
        let acceleration = (w.tv * w.n - w.v * w.t) / spread;
        self.model_force = w.force / w.n;
        self.at = w.position / w.n;
        if self.moving_mass.component_mul(&acceleration).norm() >= MIN_FORCE {
            self.moving += 1;
        } else {
            self.moving = 0;
        }
        self.recent.push(Span {
            time: w.start + w.t / w.n,
            velocity: w.v / w.n,
            position: self.at,
        });
        if self.recent.len() > WINDOWS + 1 {
            self.recent.remove(0);
        }
        self.judge(s.time)
    }

    /// A state under an application's `offset`: a rest of [`HELD_TIME`] ends, is kept, and
    /// with [`HELD_RESTS`] kept is judged.
    fn held_still(&mut self, p: &PublishedState, offset: Vector3<f64>) -> Option<Noticed> {
        let s = &p.state;
        let broken = self.held.is_some_and(|h| {
            s.time <= h.last
                || s.time - h.last > GAP_STEPS * self.step
                || (s.position - h.at).norm() > HELD_RADIUS
        });
        if broken {
            // The handle moved (or states were lost): a new rest may start here.
            self.held = None;
        }
        let h = self.held.get_or_insert(Held {
            start: s.time,
            at: s.position,
            last: s.time,
            n: 0.0,
            offset: Vector3::zeros(),
            position: Vector3::zeros(),
            low: offset,
            high: offset,
            force: Vector3::zeros(),
        });
        if h.n > 0.0 {
            self.step = self.step.min(s.time - h.last);
        }
        h.last = s.time;
        h.n += 1.0;
        h.offset += offset;
        h.position += s.position;
        h.low = h.low.inf(&offset);
        h.high = h.high.sup(&offset);
        h.force += p.gravity;
        let steady = (h.high - h.low)
            .iter()
            .zip(self.friction.iter())
            .all(|(spread, f)| *spread <= f.max(MIN_FORCE));
        if !steady {
            // The application's force is changing: a new rest starts here.
            self.held = None;
            return None;
        }
        if s.time - h.start < HELD_TIME {
            return None;
        }
        let h = self.held.take().expect("a rest");
        self.model_force = h.force / h.n;
        let rest = Rest {
            position: h.position / h.n,
            offset: h.offset / h.n,
        };
        self.rests
            .retain(|r| (r.position - rest.position).norm() >= HELD_APART);
        if self.rests.len() == HELD_RESTS {
            self.rests.remove(0);
        }
        self.rests.push(rest);
        self.judge_rests(s.time)
    }

    /// [`HELD_RESTS`] rests whose offsets agree within the friction and [`AGREEMENT`] of their
    /// mean, the mean beyond what friction could hold along each axis by [`MIN_FORCE`] (and
    /// [`MIN_SHARE`] of the model's force): the application holds a force the model misses,
    /// the same wherever the handle rests.
    fn judge_rests(&mut self, time: f64) -> Option<Noticed> {
        if self.rests.len() < HELD_RESTS {
            return None;
        }
        let missed = self.rests.iter().map(|r| r.offset).sum::<Vector3<f64>>() / HELD_RESTS as f64;
        let agree = self.rests.iter().all(|r| {
            (r.offset - missed)
                .iter()
                .zip(self.friction.iter())
                .all(|(d, f)| d.abs() <= f + AGREEMENT * missed.norm())
        });
        // What friction could not hold, along each axis.
        let beyond = |force: Vector3<f64>| {
            force.zip_map(&self.friction, |x, f| x.signum() * (x.abs() - f).max(0.0))
        };
        let beyond_friction = beyond(missed).norm();
        if !agree || beyond_friction < MIN_FORCE.max(MIN_SHARE * self.model_force.norm()) {
            return None;
        }
        // At rest nothing accelerates: no moving mass shares the payload's weight. Across
        // gravity, what friction could hold is not told from what is missed (the moves between
        // rests all stop against it the same way): only what is beyond it is read.
        let up = self.model.gravity_up();
        let along = up * missed.dot(&up);
        let at = self.rests.iter().map(|r| r.position).sum::<Vector3<f64>>() / HELD_RESTS as f64;
        let noticed = Noticed::of(
            along + beyond(missed - along),
            &at,
            &self.model,
            true,
            time,
            StaleEvidence::HeldStill,
        )?;
        self.noticed = true;
        Some(noticed)
    }

    /// The last [`WINDOWS`] steps between windows, all sliding and not the first window of their
    /// motion: a missed force that a steady model explains. Per step, its acceleration from the
    /// windows' mean velocities (a window's own slope scatters by a third of a released
    /// delta's acceleration: its velocity's noise over 40 ms), at their mean velocity,
    /// M a + f sgn(v) = −F − s(v) with F the force missed and s a speed's force, both unknown:
    /// F and s by least squares over the steps, which only a handle whose speed changes tells
    /// apart (from rest, as a released handle starts). On a point-like device s = c v, a viscous
    /// damping (c ≥ 0). On a linkage, whose released handle swings along an arc, it is the
    /// velocity product's force along v_G, k |v|² of either sign: WoodenHaptics' arm under 30 g
    /// slows its acceleration along v_G from 1.6 to 0.7 m/s² in 160 ms as it turns, which read
    /// as a damping (0.33 N·s/m) made it 3-9 g heavy.
    fn judge(&mut self, time: f64) -> Option<Noticed> {
        // The first window of a motion holds its onset (and the velocity filter's): not read.
        if self.recent.len() <= WINDOWS || self.moving <= WINDOWS + 1 {
            return None;
        }
        let steps: Vec<(Vector3<f64>, Vector3<f64>)> = self
            .recent
            .windows(2)
            .map(|pair| {
                let (a, b) = (&pair[0], &pair[1]);
                (
                    (b.velocity - a.velocity) / (b.time - a.time),
                    (a.velocity + b.velocity) / 2.0,
                )
            })
            .collect();
        let n = steps.len() as f64;
        let up = self.model.gravity_up();
        // A linkage's inertia couples the axes (its released handle swings along an arc the
        // per-axis moving masses do not hold): on a device with an arm model (whichever model
        // compensates) only what acts along v_G is read.
        let coupled = self.coupled;
        let read = |x: Vector3<f64>| if coupled { up * x.dot(&up) } else { x };
        let sliding = |v: &Vector3<f64>| v.map(|v| if v.abs() > MOVING { v.signum() } else { 0.0 });
        // f sgn(v) holds for a sliding handle only: a window at rest (its velocity the
        // encoder's noise, its slope as noisy) is not read. The delta at rest before its payload
        // grew had windows the slopes took for moving.
        if self
            .recent
            .iter()
            .any(|w| read(w.velocity).norm() <= MOVING)
        {
            return None;
        }
        // l = −M a − f sgn(v) = F + s(v): per step, l and the speed's regressor r (s = σ r).
        let speed_term = |v: &Vector3<f64>| {
            if coupled {
                up * v.norm_squared()
            } else {
                *v
            }
        };
        let readings: Vec<(Vector3<f64>, Vector3<f64>)> = steps
            .iter()
            .map(|(a, v)| {
                let l = -self.moving_mass.component_mul(a)
                    - self.sliding_friction.component_mul(&sliding(v));
                (read(l), speed_term(v))
            })
            .collect();
        let l_mean = readings.iter().map(|(l, _)| l).sum::<Vector3<f64>>() / n;
        let r_mean = readings.iter().map(|(_, r)| r).sum::<Vector3<f64>>() / n;
        let (mut covariance, mut variance) = (0.0, 0.0);
        for (l, r) in &readings {
            covariance += (l - l_mean).dot(&(r - r_mean));
            variance += (r - r_mean).norm_squared();
        }
        let sigma = match (variance > 0.0, coupled) {
            (false, _) => 0.0,
            (true, true) => covariance / variance,
            (true, false) => (covariance / variance).max(0.0),
        };
        let missed = l_mean - r_mean * sigma;
        let steady = readings
            .iter()
            .all(|(l, r)| (l - missed - r * sigma).norm() <= AGREEMENT * missed.norm());
        if !steady || missed.norm() < MIN_FORCE.max(MIN_SHARE * self.model_force.norm()) {
            return None;
        }
        // A force beyond the friction moves the released handle, faster and faster. A handle at
        // rest whose velocity reads its encoder's noise, or one that creeps, does not: its
        // steps' accelerations scatter about zero (each alone may pass MIN_FORCE), it covers
        // less than half the way its velocities say, and the friction term f sgn(v) would read
        // as a force (the simulated delta left alone: 18-24 g).
        let v_mean = steps.iter().map(|(_, v)| read(*v)).sum::<Vector3<f64>>() / n;
        if v_mean.norm() == 0.0 {
            return None;
        }
        let heading = v_mean.normalize();
        let speeding_up = steps
            .iter()
            .map(|(a, _)| read(self.moving_mass.component_mul(a)))
            .sum::<Vector3<f64>>()
            / n;
        let (first, last) = (self.recent[0], self.recent[self.recent.len() - 1]);
        let covered = read(last.position - first.position).dot(&heading);
        if speeding_up.dot(&heading) < MIN_FORCE
            || covered < 0.5 * v_mean.norm() * (last.time - first.time)
        {
            return None;
        }
        // A payload m_p rides along, and friction f_s = f sgn(v) does not:
        // (M + m_p) a + f_s = −F − c v, so what was read is (M F − m_p f_s) / (M + m_p), and
        // F · v_G = m_p g gives m_p (M the moving mass along v_G).
        let mass = up.dot(&self.moving_mass.component_mul(&up));
        let friction = read(
            self.sliding_friction
                .component_mul(&sliding(&last.velocity)),
        );
        let along = missed.dot(&up);
        let denominator = mass * self.model.grid.g - along - friction.dot(&up);
        if denominator <= 0.0 {
            // More than a payload could show, rising faster than friction and the moving
            // mass's weight allow: not a payload's signature.
            return None;
        }
        let payload = mass * along / denominator;
        // Each axis with its own moving mass (along v_G alone on a linkage).
        let masses = if coupled {
            Vector3::repeat(mass)
        } else {
            self.moving_mass
        };
        let missed = (missed.component_mul(&masses.add_scalar(payload)) + friction * payload)
            .component_div(&masses);
        let noticed = Noticed::of(
            missed,
            &self.at,
            &self.model,
            !coupled,
            time,
            StaleEvidence::Released,
        )?;
        self.noticed = true;
        Some(noticed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::OutsideGrid;
    use crate::control::DeviceState;
    use crate::grid::MassGrid;

    /// 120 g over a 3 × 3 × 3 lattice, 40 mm apart.
    fn uniform_grid() -> MassGrid {
        MassGrid::uniform(
            0.12,
            9.81,
            Vector3::z(),
            Vector3::repeat(-0.04),
            0.04,
            [3, 3, 3],
        )
    }

    fn watch() -> ModelWatch {
        let file = GridFile::from(uniform_grid());
        let model = GravityModel::configured(file.clone(), None, OutsideGrid::HoldNearest).unwrap();
        ModelWatch::new(&file, &model)
    }

    /// A sliding handle meets the survey strokes' sliding friction where the file records it,
    /// the bands' half-widths (usually 5–30 % more) where it does not or its is not a
    /// friction; a resting one is held by up to the bands' half-widths either way.
    #[test]
    fn the_watch_takes_the_sliding_friction_over_the_bands() {
        let friction = |sliding: Option<[f64; 3]>| {
            let mut file = GridFile::from(uniform_grid());
            file.calibration = Some(crate::grid::CalibrationRecord {
                friction_n: Some([0.1, 0.1, 0.12]),
                sliding_friction_n: sliding,
                ..Default::default()
            });
            let model =
                GravityModel::configured(file.clone(), None, OutsideGrid::HoldNearest).unwrap();
            let watch = ModelWatch::new(&file, &model);
            assert_eq!(watch.friction, Vector3::new(0.1, 0.1, 0.12));
            watch.sliding_friction
        };
        assert_eq!(
            friction(Some([0.08, 0.09, 0.1])),
            Vector3::new(0.08, 0.09, 0.1)
        );
        assert_eq!(friction(None), Vector3::new(0.1, 0.1, 0.12));
        assert_eq!(
            friction(Some([0.08, f64::NAN, 0.1])),
            Vector3::new(0.1, 0.1, 0.12)
        );
    }

    /// A handle released at `t0` under a force `missed` the model does not hold, 1 kHz.
    fn falling(missed: Vector3<f64>, mass: f64, ticks: u64) -> Vec<PublishedState> {
        (0..ticks)
            .map(|n| {
                let time = n as f64 * 1e-3;
                let state = DeviceState {
                    tick: n,
                    time,
                    host_time: time,
                    position: -missed / mass * (time * time / 2.0),
                    velocity: -missed / mass * time,
                    status: Status::default().with(Status::MOTORS_ENABLED, true),
                };
                PublishedState {
                    state,
                    force: Vector3::z() * (0.12 * 9.81),
                    gravity: Vector3::z() * (0.12 * 9.81),
                    offset_seq: 0,
                    gravity_only: true,
                }
            })
            .collect()
    }

    #[test]
    fn a_steady_sinking_is_read_as_a_payload_once() {
        let mut w = watch();
        // Without damping the handle sinks at a constant acceleration.
        // 30 g more than the model holds: m_p g down, on a moving mass of 0.15 kg.
        let weight = Vector3::z() * (0.03 * 9.81);
        let found: Vec<Noticed> = falling(weight, 0.15, 400)
            .iter()
            .filter_map(|p| w.observe(p))
            .collect();
        assert_eq!(found.len(), 1, "{found:?}");
        // The watch knows the moving mass without the payload (0.12 kg) and takes it in.
        assert!((found[0].payload_kg - 0.03).abs() < 1e-3, "{found:?}");
        assert!(found[0].sideways_n < 1e-9, "{found:?}");
    }

    /// Gravity turned 3° about x: what the model misses is the 120 g handle's weight turned, and
    /// the watch reads it back as that tilt (and no payload).
    #[test]
    fn a_released_handle_sliding_sideways_is_read_as_a_tilt() {
        let mut w = watch();
        let weight = Vector3::z() * (0.12 * 9.81);
        let turned = nalgebra::Rotation3::new(Vector3::x() * 3f64.to_radians());
        let missed = turned * weight - weight;
        let found: Vec<Noticed> = falling(missed, 0.12, 400)
            .iter()
            .filter_map(|p| w.observe(p))
            .collect();
        assert_eq!(found.len(), 1, "{found:?}");
        let tilt = found[0].tilt;
        assert!((tilt.norm().to_degrees() - 3.0).abs() < 0.01, "{found:?}");
        assert!((tilt.normalize() - Vector3::x()).norm() < 1e-3, "{found:?}");
        assert!(found[0].payload_kg.abs() < 1e-6, "{found:?}");
    }

    /// Against sliding friction f (its calibration's) a heavier handle sinks slower:
    /// (M + m_p) a = −(m_p g − f) along z; the watch, knowing M and f, reads m_p exactly.
    #[test]
    fn a_sinking_against_friction_is_read_as_its_payload() {
        let mut w = watch();
        let friction = 0.1;
        w.sliding_friction = Vector3::new(0.05, 0.05, friction);
        let (payload, moving) = (0.03, 0.12);
        let slowed = Vector3::z() * (payload * 9.81 - friction);
        let found: Vec<Noticed> = falling(slowed, moving + payload, 400)
            .iter()
            .filter_map(|p| w.observe(p))
            .collect();
        assert_eq!(found.len(), 1, "{found:?}");
        assert!((found[0].payload_kg - payload).abs() < 1e-4, "{found:?}");
        assert!(found[0].tilt.norm() < 1e-6, "{found:?}");
    }

    /// A delta-like handle (0.15 kg, 0.19 N of sliding friction) sinking under 30 g, its
    /// velocity read with 5 mm/s of noise a sample: each 40 ms window's own slope scatters by
    /// an eighth of its acceleration, and four of them took that scatter for a damping (16 of 20
    /// seeds within 5 %, the worst 11.7 % off). Read from the windows' means, 20 of 20 are
    /// within 5 % (the worst 4.9 %, most under 1 %).
    #[test]
    fn a_sinking_read_through_a_noisy_velocity_is_read_from_its_windows_means() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let (payload, moving, friction) = (0.03, 0.15, 0.19);
        let slowed = Vector3::z() * (payload * 9.81 - friction);
        let mut worst: f64 = 0.0;
        for seed in 0..20 {
            let mut w = watch();
            w.moving_mass = Vector3::repeat(moving);
            w.sliding_friction = Vector3::new(0.15, 0.15, friction);
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
            let noise = Normal::new(0.0, 0.005).unwrap();
            let found: Vec<Noticed> = falling(slowed, moving + payload, 600)
                .into_iter()
                .filter_map(|mut p| {
                    p.state.velocity.z += noise.sample(&mut rng);
                    w.observe(&p)
                })
                .collect();
            assert_eq!(found.len(), 1, "seed {seed}: {found:?}");
            worst = worst.max((found[0].payload_kg / payload - 1.0).abs());
        }
        assert!(
            worst < 0.05,
            "the worst of 20 readings {:.1} % off",
            worst * 100.0
        );
    }

    /// With viscous damping c the handle approaches its sinking speed: v = −(F / c)(1 − e^{−t/τ}),
    /// τ = (M + m_p) / c; what it does before it gets there tells F from c.
    #[test]
    fn a_damped_sinking_is_read_as_a_payload() {
        let (weight, moving, damping) = (0.03 * 9.81, 0.15, 1.0);
        let tau = moving / damping;
        let mut w = watch();
        let found: Vec<Noticed> = (0..400u64)
            .map(|n| {
                let time = n as f64 * 1e-3;
                let sinking = -weight / damping * (1.0 - (-time / tau).exp());
                let sunk = -weight / damping * (time - tau * (1.0 - (-time / tau).exp()));
                PublishedState {
                    state: DeviceState {
                        tick: n,
                        time,
                        host_time: time,
                        position: Vector3::z() * sunk,
                        velocity: Vector3::z() * sinking,
                        status: Status::default().with(Status::MOTORS_ENABLED, true),
                    },
                    force: Vector3::z() * (0.12 * 9.81),
                    gravity: Vector3::z() * (0.12 * 9.81),
                    offset_seq: 0,
                    gravity_only: true,
                }
            })
            .filter_map(|p| w.observe(&p))
            .collect();
        assert_eq!(found.len(), 1, "{found:?}");
        assert!((found[0].payload_kg - 0.03).abs() < 1e-3, "{found:?}");
    }

    /// A frictional handle at rest whose velocity reads a few mm/s of noise, one way for a
    /// while, with accelerations scattered about zero: the friction term of that "motion"
    /// (0.19 N) is not a missed force. The simulated delta left alone looked like this.
    #[test]
    fn a_handle_at_rest_with_a_noisy_velocity_says_nothing() {
        let mut w = watch();
        w.friction = Vector3::new(0.15, 0.15, 0.19);
        w.sliding_friction = w.friction;
        let noticed = (0..2000u64).find_map(|n| {
            let time = n as f64 * 1e-3;
            let wobble = 0.003 * (2.0 * std::f64::consts::PI * time / 0.16).sin();
            w.observe(&PublishedState {
                state: DeviceState {
                    tick: n,
                    time,
                    host_time: time,
                    position: Vector3::zeros(),
                    velocity: Vector3::z() * (-0.0045 + wobble),
                    status: Status::default().with(Status::MOTORS_ENABLED, true),
                },
                force: Vector3::z() * (0.12 * 9.81),
                gravity: Vector3::z() * (0.12 * 9.81),
                offset_seq: 0,
                gravity_only: true,
            })
        });
        assert!(noticed.is_none(), "{noticed:?}");
    }

    /// A model 2 % off (a calibration a little out between its vertices) is not stale.
    #[test]
    fn a_model_within_its_accuracy_raises_no_alarm() {
        let mut w = watch();
        let off = Vector3::z() * (0.02 * 0.12 * 9.81);
        assert!(falling(off, 0.12, 1000)
            .iter()
            .all(|p| w.observe(p).is_none()));
    }

    #[test]
    fn a_handle_at_rest_or_moved_by_an_application_says_nothing() {
        let mut w = watch();
        assert!(falling(Vector3::zeros(), 0.12, 1000)
            .iter()
            .all(|p| w.observe(p).is_none()));
        let mut w = watch();
        let held = falling(Vector3::z() * 0.3, 0.15, 1000);
        assert!(held
            .iter()
            .map(|p| PublishedState {
                gravity_only: false,
                ..*p
            })
            .all(|p| w.observe(&p).is_none()));
    }

    /// The handle at rest at each of `places` in turn, held there by an application's offset
    /// (the matching one of `offsets`) for half a second, moving at 10 mm/s for 20 ms between:
    /// the states a watch reads, 1 kHz.
    fn held_at(places: &[Vector3<f64>], offsets: &[Vector3<f64>]) -> Vec<PublishedState> {
        let gravity = Vector3::z() * (0.12 * 9.81);
        let mut states = Vec::new();
        for (place, offset) in places.iter().zip(offsets) {
            for k in 0..520u64 {
                let n = states.len() as u64;
                let time = n as f64 * 1e-3;
                let moving = k < 20;
                states.push(PublishedState {
                    state: DeviceState {
                        tick: n,
                        time,
                        host_time: time,
                        position: *place,
                        velocity: if moving {
                            Vector3::x() * 0.01
                        } else {
                            Vector3::zeros()
                        },
                        status: Status::default().with(Status::MOTORS_ENABLED, true),
                    },
                    force: gravity + offset,
                    gravity,
                    offset_seq: 1,
                    gravity_only: false,
                });
            }
        }
        states
    }

    fn places() -> [Vector3<f64>; 3] {
        [0.0, 0.01, 0.02].map(|x| Vector3::new(x, 0.0, 0.0))
    }

    /// 30 g more than the model holds, held still by an application at three places: the
    /// offsets hold its weight, give or take the friction (20 mN here), and read as the payload.
    #[test]
    fn an_application_holding_a_heavier_handle_still_at_three_places_shows_the_payload() {
        let mut w = watch();
        w.friction = Vector3::repeat(0.02);
        let weight = Vector3::z() * (0.03 * 9.81);
        let offsets = [0.015, -0.01, 0.0].map(|f| weight + Vector3::new(0.0, 0.0, f));
        let found: Vec<Noticed> = held_at(&places(), &offsets)
            .iter()
            .filter_map(|p| w.observe(p))
            .collect();
        assert_eq!(found.len(), 1, "{found:?}");
        assert_eq!(found[0].evidence, StaleEvidence::HeldStill);
        assert!(
            (found[0].payload_kg - 0.03).abs() < 0.02 / 9.81,
            "{found:?}"
        );
        assert!(found[0].sideways_n < 1e-9, "{found:?}");
    }

    /// A hand holds the handle with a different force at each place; a stop holds it at one
    /// place; friction alone holds an offset within it: none of these is a missed force.
    #[test]
    fn a_hand_a_stop_or_friction_holding_the_handle_says_nothing() {
        let silent = |places: &[Vector3<f64>], offsets: &[Vector3<f64>]| {
            let mut w = watch();
            w.friction = Vector3::repeat(0.02);
            held_at(places, offsets)
                .iter()
                .all(|p| w.observe(p).is_none())
        };
        let up = |f: f64| Vector3::z() * f;
        assert!(silent(&places(), &[up(0.1), up(0.3), up(0.5)]));
        assert!(silent(&[Vector3::zeros(); 3], &[up(0.3); 3]));
        assert!(silent(&places(), &[up(0.015), up(-0.015), up(0.01)]));
        // The same three rests beside a payload's weight are read (the cases above are not
        // silent for want of rests).
        assert!(!silent(&places(), &[up(0.3); 3]));
    }
}
