//! Exploration of a workspace of unknown shape (`calibration.workspace = "explore"`): after the
//! initialisation, the hold walks the handle over the lattice X_C + L (n, m, p) the grid will
//! use, one edge at a time, depth first: from the vertex it is at, it tries each face
//! neighbour it has not reached yet, at [`PROBE_SPEED`]. A move that arrives adds the
//! neighbour to the map and goes on from there; a move the handle stops following has met a
//! mechanical stop, a joint limit or an obstacle, and the hold glides back to where it came
//! from along the line it just travelled. When every neighbour of a vertex has been tried, the
//! hold returns along the edge it came by. The map that grows so follows any shape the lattice
//! can resolve: a bowl, a shell, a box with a wall in it.
//!
//! A stop is met when the handle stops following the reference while the hold's force grows:
//! the reference runs ahead of the handle by more than [`CONTACT_LAG`] (or by what half the
//! push limit stretches the hold by, if that is less). The reference's speed is the handle's
//! speed when it meets the stop, so no stop is struck faster than [`CONTACT_SPEED`]. Returns
//! run along lines the handle has just travelled, so they are faster. A vertex outside the
//! configured box (`device.workspace_*_mm`) is never tried: exploration never leaves the box
//! the user allowed.
//!
//! Each reached vertex keeps its *clearance*: the shortest distance a move from it ran before
//! a stop, or to the configured box along an axis; [`GridPlan::explore`](super::GridPlan::explore)
//! calibrates the vertices whose clearance is at least [`MARGIN`] and extrapolates the others.

use nalgebra::Vector3;

use super::machine::Glide;
use super::plan::MAX_EXPLORED_SIDE;
use crate::control::pd::AxisGains;
use crate::control::DeviceState;

/// Speed of the reference along a move to a vertex not reached yet, m/s: the speed the handle
/// meets a stop at.
pub const PROBE_SPEED: f64 = 0.015;
/// The bound on the handle's speed at any contact during exploration, m/s (documented; the
/// tests read the plant's contact log against it).
pub const CONTACT_SPEED: f64 = 0.020;
/// Time constant of a move's speed ramp from rest, s.
const PROBE_RAMP: f64 = 0.2;
/// How far the reference may run ahead of the handle before it counts as a stop, m.
pub const CONTACT_LAG: f64 = 0.003;
/// A move arrives when the handle comes this close to the vertex after the reference has, m...
const ARRIVAL: f64 = 0.001;
/// ... within this long, s; otherwise something short of the vertex holds the handle (a stop
/// nearer than the lag that counts as one).
const ARRIVAL_TIME: f64 = 1.5;
/// Share of the push limit the hold may push a stop with before it counts as met.
const CONTACT_PUSH_SHARE: f64 = 0.5;
/// Peak speed of a return along an edge the handle has travelled from end to end, m/s: nothing
/// is in the way there. The calibration's moves along such an edge run as fast. After a stop, the return to the vertex the move set off from is no
/// faster than a move ([`PROBE_SPEED`]): the hold lets go of the stop slowly.
pub const RETURN_SPEED: f64 = 0.045;
/// Shortest return, s.
const MIN_RETURN: f64 = 0.3;
/// Integral time of the hold's integral term, s: it takes up the change of the holding force
/// over the workspace (the hold's gravity term is the load at X_C).
const INTEGRAL_TIME: f64 = 1.0;
/// Distance kept from every stop a move met and from the configured box by every vertex
/// calibrated, m: a vertex's strokes reach 4 mm from it and its band pushes a millimetre or two.
pub const MARGIN: f64 = 0.012;
/// Lattice indices the map can hold along an axis, around X_C: −(SIDE − 1) / 2 … (SIDE − 1) / 2.
const SIDE: usize = 2 * MAX_EXPLORED_SIDE - 1;
/// Most vertices reached along an axis: the grid adds a layer on each side for the stops
/// beyond them and holds at most [`MAX_EXPLORED_SIDE`].
const MAX_REACHED_SIDE: i32 = MAX_EXPLORED_SIDE as i32 - 2;
/// The six face neighbours, in the order they are tried.
const NEIGHBOURS: [[i32; 3]; 6] = [
    [1, 0, 0],
    [-1, 0, 0],
    [0, 1, 0],
    [0, -1, 0],
    [0, 0, 1],
    [0, 0, -1],
];

/// What exploration knows of one lattice vertex.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Cell {
    Unknown,
    /// The handle stopped on the way to it from every vertex that tried it.
    Blocked,
    /// The handle reached it; the shortest free run from it, m, the neighbours it has tried
    /// and those the handle has travelled to or from it (a bit per entry of [`NEIGHBOURS`]).
    Reached {
        clearance: f64,
        tried: u8,
        walked: u8,
    },
}

/// The reachable workspace as exploration found it: the lattice vertices the handle reached,
/// each with its clearance, inside the configured box.
#[derive(Clone, Debug, PartialEq)]
pub struct WorkspaceMap {
    /// X_C, where the handle rested after the initialisation, m: vertex (0, 0, 0).
    pub centre: Vector3<f64>,
    /// L, m.
    pub spacing: f64,
    /// The configured box (`device.workspace_*_mm`), m.
    pub bounds: (Vector3<f64>, Vector3<f64>),
    cells: Vec<Cell>,
    /// How many vertices the handle reached.
    reached: usize,
    /// Lowest and highest index reached along each axis.
    reached_span: ([i32; 3], [i32; 3]),
    /// The box of the vertices reached and the points where a stop ended a move, m.
    extent: (Vector3<f64>, Vector3<f64>),
}

impl WorkspaceMap {
    /// An empty map of the lattice of `spacing` (m) inside `bounds` (m); allocates all it will
    /// hold.
    pub fn new(bounds: (Vector3<f64>, Vector3<f64>), spacing: f64) -> Self {
        Self {
            centre: Vector3::zeros(),
            spacing,
            bounds,
            cells: vec![Cell::Unknown; SIDE * SIDE * SIDE],
            reached: 0,
            reached_span: ([0; 3], [0; 3]),
            extent: (Vector3::zeros(), Vector3::zeros()),
        }
    }

    /// Forget everything; the handle is at `centre`, vertex (0, 0, 0).
    fn reset(&mut self, centre: Vector3<f64>) {
        self.centre = centre;
        self.cells.fill(Cell::Unknown);
        self.reached = 0;
        self.reached_span = ([0; 3], [0; 3]);
        self.extent = (centre, centre);
        self.reach([0; 3]);
    }

    fn slot(&self, k: [i32; 3]) -> Option<usize> {
        let half = (SIDE as i32 - 1) / 2;
        if k.iter().any(|c| c.abs() > half) {
            return None;
        }
        let u = k.map(|c| (c + half) as usize);
        Some(u[0] + SIDE * (u[1] + SIDE * u[2]))
    }

    fn cell(&self, k: [i32; 3]) -> Option<Cell> {
        self.slot(k).map(|n| self.cells[n])
    }

    /// Where vertex `k` is, m.
    pub fn position(&self, k: [i32; 3]) -> Vector3<f64> {
        self.centre + Vector3::new(f64::from(k[0]), f64::from(k[1]), f64::from(k[2])) * self.spacing
    }

    fn inside_bounds(&self, x: &Vector3<f64>) -> bool {
        let (lo, hi) = self.bounds;
        (0..3).all(|a| x[a] >= lo[a] && x[a] <= hi[a])
    }

    fn reach(&mut self, k: [i32; 3]) {
        if let Some(n) = self.slot(k) {
            if !matches!(self.cells[n], Cell::Reached { .. }) {
                self.cells[n] = Cell::Reached {
                    clearance: f64::INFINITY,
                    tried: 0,
                    walked: 0,
                };
                self.reached += 1;
            }
        }
        let (lo, hi) = &mut self.reached_span;
        for a in 0..3 {
            lo[a] = lo[a].min(k[a]);
            hi[a] = hi[a].max(k[a]);
        }
        self.widen(&self.position(k));
    }

    fn block(&mut self, k: [i32; 3]) {
        if let Some(n) = self.slot(k) {
            if self.cells[n] == Cell::Unknown {
                self.cells[n] = Cell::Blocked;
            }
        }
    }

    /// The clearance of vertex `k` is at most `free` m.
    fn clear(&mut self, k: [i32; 3], free: f64) {
        if let Some(n) = self.slot(k) {
            if let Cell::Reached { clearance, .. } = &mut self.cells[n] {
                *clearance = clearance.min(free);
            }
        }
    }

    /// Whether vertex `k` has tried its neighbour `step` (an index into [`NEIGHBOURS`]); marks
    /// it tried.
    fn try_once(&mut self, k: [i32; 3], step: usize) -> bool {
        match self.slot(k).map(|n| &mut self.cells[n]) {
            Some(Cell::Reached { tried, .. }) => {
                let before = *tried & (1 << step) != 0;
                *tried |= 1 << step;
                before
            }
            _ => true,
        }
    }

    fn widen(&mut self, x: &Vector3<f64>) {
        let (lo, hi) = self.extent;
        self.extent = (lo.inf(x), hi.sup(x));
    }

    /// The handle travelled the edge from vertex `k` along `step` (an index into
    /// [`NEIGHBOURS`]) from end to end.
    fn walk(&mut self, k: [i32; 3], step: usize) {
        let n = NEIGHBOURS[step];
        let other = [0, 1, 2].map(|a| k[a] + n[a]);
        // NEIGHBOURS pairs each direction with its opposite: 0–1, 2–3, 4–5.
        for (end, bit) in [(k, step), (other, step ^ 1)] {
            if let Some(Cell::Reached { walked, .. }) = self.slot(end).map(|s| &mut self.cells[s]) {
                *walked |= 1 << bit;
            }
        }
    }

    /// The lattice vertex within `tolerance` (m) of `x`, if any.
    fn vertex_at(&self, x: &Vector3<f64>, tolerance: f64) -> Option<[i32; 3]> {
        let u = (x - self.centre) / self.spacing;
        let k = [0, 1, 2].map(|a| u[a].round() as i32);
        ((self.position(k) - x).norm() <= tolerance).then_some(k)
    }

    /// Whether the handle has travelled the straight line from `a` to `b` (m) end to end: they
    /// are neighbouring vertices (`a` within 2 mm of one) joined by an edge a move of the walk
    /// arrived along.
    pub fn walked(&self, a: &Vector3<f64>, b: &Vector3<f64>) -> bool {
        let (Some(ka), Some(kb)) = (
            self.vertex_at(a, 2.0 * ARRIVAL),
            self.vertex_at(b, 1e-6 * self.spacing),
        ) else {
            return false;
        };
        let step = [0, 1, 2].map(|c| kb[c] - ka[c]);
        let Some(s) = NEIGHBOURS.iter().position(|&n| n == step) else {
            return false;
        };
        matches!(self.cell(ka), Some(Cell::Reached { walked, .. }) if walked & (1 << s) != 0)
    }

    /// Whether `x` is a vertex the handle reached with at least `margin` (m) of clearance.
    pub fn contains(&self, x: &Vector3<f64>, margin: f64) -> bool {
        let Some(k) = self.vertex_at(x, 1e-6 * self.spacing) else {
            return false;
        };
        matches!(self.cell(k), Some(Cell::Reached { clearance, .. }) if clearance >= margin)
    }

    /// The box of the vertices reached and of the points where a stop ended a move, m.
    pub fn extent(&self) -> (Vector3<f64>, Vector3<f64>) {
        self.extent
    }

    /// How many vertices the handle reached.
    pub fn reached(&self) -> usize {
        self.reached
    }
}

/// One move of the exploration: from a reached vertex toward a neighbour along `direction`
/// (a unit axis), the `run` m the handle went, and whether a stop ended it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Probe {
    pub from: Vector3<f64>,
    pub direction: Vector3<f64>,
    pub run: f64,
    pub stopped: bool,
}

/// The leg in progress.
#[derive(Clone, Copy, Debug)]
enum Leg {
    /// From vertex `from` toward its neighbour `to`, since `start`.
    Out {
        from: [i32; 3],
        to: [i32; 3],
        step: usize,
        start: f64,
    },
    /// Back to vertex `to` along a line just travelled.
    Back { to: [i32; 3], glide: Glide },
}

/// Runs the walk (module docs). Built off the servo thread; [`Explorer::tick`] does not
/// allocate.
#[derive(Clone, Debug)]
pub struct Explorer {
    map: WorkspaceMap,
    /// The vertices the walk came by, X_C first: where it returns once the current vertex has
    /// tried every neighbour.
    trail: Vec<[i32; 3]>,
    leg: Leg,
    /// The last move finished, until taken.
    probed: Option<Probe>,
    probes: usize,
    stopped: usize,
    /// The hold's integral term, N, and the time of the last tick, s.
    integral: Vector3<f64>,
    last_time: f64,
    /// The most the integral term and a move's push may add to the load, N.
    push_limit: f64,
}

impl Explorer {
    /// A walk over the lattice of `spacing` (m) inside `bounds` (m); `push_limit` is the most
    /// calibration pushes beyond the forces it holds, N. [`Explorer::begin`] starts it.
    pub fn new(bounds: (Vector3<f64>, Vector3<f64>), spacing: f64, push_limit: f64) -> Self {
        Self {
            map: WorkspaceMap::new(bounds, spacing),
            trail: Vec::with_capacity(SIDE * SIDE * SIDE),
            leg: Leg::Back {
                to: [0; 3],
                glide: Glide {
                    from: Vector3::zeros(),
                    to: Vector3::zeros(),
                    start: 0.0,
                    duration: 0.0,
                },
            },
            probed: None,
            probes: 0,
            stopped: 0,
            integral: Vector3::zeros(),
            last_time: 0.0,
            push_limit,
        }
    }

    /// Start the walk from `centre` (m, the handle at rest there) at time `t`, forgetting any
    /// earlier one.
    pub fn begin(&mut self, centre: Vector3<f64>, t: f64) {
        self.map.reset(centre);
        self.trail.clear();
        self.probed = None;
        self.probes = 0;
        self.stopped = 0;
        self.integral = Vector3::zeros();
        self.last_time = t;
        self.leg = Leg::Back {
            to: [0; 3],
            glide: Glide {
                from: centre,
                to: centre,
                start: t,
                duration: 0.0,
            },
        };
    }

    /// The map so far (complete once [`Explorer::tick`] has returned `None`).
    pub fn map(&self) -> &WorkspaceMap {
        &self.map
    }

    /// Moves tried, and how many of them met a stop.
    pub fn probes(&self) -> (usize, usize) {
        (self.probes, self.stopped)
    }

    /// The move that ended at the last tick, once.
    pub fn take_probe(&mut self) -> Option<Probe> {
        self.probed.take()
    }

    /// From vertex `k` at time `t`: the next neighbour to try, or the return along the trail;
    /// false once the walk is back at X_C with nothing left to try.
    fn next_leg(&mut self, k: [i32; 3], t: f64) -> bool {
        let (lo, hi) = self.map.reached_span;
        for (s, step) in NEIGHBOURS.into_iter().enumerate() {
            let n = [0, 1, 2].map(|a| k[a] + step[a]);
            let Some(cell) = self.map.cell(n) else {
                continue;
            };
            if matches!(cell, Cell::Reached { .. }) || self.map.try_once(k, s) {
                continue;
            }
            // The grid holds so many vertices along an axis: the workspace beyond is left to the
            // grid's faces, and is no stop.
            if (0..3).any(|a| n[a].max(hi[a]) - n[a].min(lo[a]) + 1 > MAX_REACHED_SIDE) {
                continue;
            }
            let to = self.map.position(n);
            if !self.map.inside_bounds(&to) {
                // The configured box ends the workspace between the two: as near as a stop.
                let a = (0..3).find(|&a| step[a] != 0).expect("a face neighbour");
                let (b_lo, b_hi) = self.map.bounds;
                let wall = if step[a] > 0 { b_hi[a] } else { b_lo[a] };
                let free = (wall - self.map.position(k)[a]).abs();
                self.map.clear(k, free);
                continue;
            }
            self.leg = Leg::Out {
                from: k,
                to: n,
                step: s,
                start: t,
            };
            return true;
        }
        match self.trail.pop() {
            Some(back) => {
                self.leg = Leg::Back {
                    to: back,
                    glide: self.glide(self.map.position(k), back, t, RETURN_SPEED),
                };
                true
            }
            None => false,
        }
    }

    /// A glide from `from` to vertex `to` at time `t`, peaking at `speed` (m/s).
    fn glide(&self, from: Vector3<f64>, to: [i32; 3], t: f64, speed: f64) -> Glide {
        let to = self.map.position(to);
        Glide {
            from,
            to,
            start: t,
            duration: (1.875 * (to - from).norm() / speed).max(MIN_RETURN),
        }
    }

    /// The hold's force this tick with the hold's `gains` and the load at X_C `load`; `None`
    /// once the walk is over (the handle is back at X_C).
    pub fn tick(
        &mut self,
        s: &DeviceState,
        gains: &AxisGains,
        load: &Vector3<f64>,
    ) -> Option<Vector3<f64>> {
        let dt = (s.time - self.last_time).max(0.0);
        self.last_time = s.time;
        let (target, velocity) = match self.leg {
            Leg::Out {
                from,
                to,
                step,
                start,
            } => {
                let origin = self.map.position(from);
                let d = self.map.position(to) - origin;
                let length = d.norm();
                let d = d / length;
                let tau = (s.time - start).max(0.0);
                let ramp = 1.0 - (-tau / PROBE_RAMP).exp();
                let along = PROBE_SPEED * (tau - PROBE_RAMP * ramp);
                let target = origin + d * along.min(length);
                // The whole tracking error, not only its part along the move: a handle turned
                // aside by a stop oblique to the move is held there too.
                let lag = (target - s.position).norm();
                let stiffest = gains.stiffness.max();
                let lag_limit = CONTACT_LAG.min(CONTACT_PUSH_SHARE * self.push_limit / stiffest);
                // The reference is there: the handle must follow it to the vertex, or it is held
                // short of it by a stop nearer than the lag limit.
                let arrival = start + PROBE_RAMP + length / PROBE_SPEED;
                let late = along >= length && s.time > arrival + ARRIVAL_TIME;
                if lag > lag_limit || late {
                    // Where the handle rests is on the workspace's boundary.
                    let run = (s.position - origin).norm();
                    self.map.block(to);
                    self.map.clear(from, run);
                    self.map.widen(&s.position);
                    self.finish_probe(origin, d, run, true);
                    // Back from the reference, not the handle: the hold lets go of the stop as
                    // smoothly as it pressed on it (a set point moved onto the handle at once
                    // lets the stop throw the handle off and the load bring it back hard).
                    self.leg = Leg::Back {
                        to: from,
                        glide: self.glide(target, from, s.time, PROBE_SPEED),
                    };
                    (target, Vector3::zeros())
                } else if along >= length && lag < ARRIVAL {
                    self.map.reach(to);
                    self.map.walk(from, step);
                    self.trail.push(from);
                    self.finish_probe(origin, d, length, false);
                    self.next_leg(to, s.time);
                    (target, Vector3::zeros())
                } else if along >= length {
                    (target, Vector3::zeros())
                } else {
                    (target, d * PROBE_SPEED * ramp)
                }
            }
            Leg::Back { to, glide } => {
                if glide.progress(s.time) >= 1.0 && !self.next_leg(to, s.time) {
                    return None;
                }
                (glide.at(s.time), Vector3::zeros())
            }
        };
        let error = (target - s.position).component_mul(&gains.stiffness);
        self.integral += error * (dt / INTEGRAL_TIME);
        if self.integral.norm() > self.push_limit {
            self.integral *= self.push_limit / self.integral.norm();
        }
        let mut relative = *s;
        relative.velocity -= velocity;
        Some(gains.pd_force(&target, &relative, &(load + self.integral)))
    }

    fn finish_probe(&mut self, from: Vector3<f64>, direction: Vector3<f64>, run: f64, stop: bool) {
        self.probes += 1;
        self.stopped += usize::from(stop);
        self.probed = Some(Probe {
            from,
            direction,
            run,
            stopped: stop,
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn map() -> WorkspaceMap {
        let mut map = WorkspaceMap::new((Vector3::repeat(-0.1), Vector3::repeat(0.1)), 0.02);
        map.reset(Vector3::new(0.001, 0.0, 0.0));
        map
    }

    #[test]
    fn a_reached_vertex_is_in_the_map_with_its_clearance() {
        let mut map = map();
        map.reach([1, 0, 0]);
        map.reach([2, 0, 0]);
        map.clear([2, 0, 0], 0.005);
        let at = |k| map.position(k);
        assert!(map.contains(&at([0, 0, 0]), MARGIN));
        assert!(map.contains(&at([1, 0, 0]), MARGIN));
        // A stop 5 mm beyond it: reached, not calibrated.
        assert!(!map.contains(&at([2, 0, 0]), MARGIN));
        assert!(map.contains(&at([2, 0, 0]), 0.004));
        // Never reached, or off the lattice.
        assert!(!map.contains(&at([0, 1, 0]), 0.0));
        assert!(!map.contains(&(at([1, 0, 0]) + Vector3::x() * 0.005), 0.0));
        assert_eq!(map.reached(), 3);
        let (lo, hi) = map.extent();
        assert_eq!((lo, hi), (at([0, 0, 0]), at([2, 0, 0])));
    }

    #[test]
    fn a_blocked_vertex_reached_later_from_elsewhere_counts_as_reached() {
        let mut map = map();
        map.block([0, 1, 0]);
        assert!(!map.contains(&map.position([0, 1, 0]), 0.0));
        map.reach([0, 1, 0]);
        assert!(map.contains(&map.position([0, 1, 0]), MARGIN));
        // Reaching it again keeps the clearance found.
        map.clear([0, 1, 0], 0.003);
        map.reach([0, 1, 0]);
        assert!(!map.contains(&map.position([0, 1, 0]), MARGIN));
    }

    #[test]
    fn an_edge_travelled_end_to_end_is_walked_both_ways_and_no_other() {
        let mut map = map();
        map.reach([1, 0, 0]);
        map.walk([0, 0, 0], 0);
        map.reach([0, 1, 0]);
        let at = |k| map.position(k);
        assert!(map.walked(&at([0, 0, 0]), &at([1, 0, 0])));
        assert!(map.walked(&at([1, 0, 0]), &at([0, 0, 0])));
        // From a handle resting 1 mm off the vertex.
        assert!(map.walked(&(at([1, 0, 0]) + Vector3::y() * 0.001), &at([0, 0, 0])));
        // Reached, but never travelled between; not neighbours; off the vertex.
        assert!(!map.walked(&at([0, 0, 0]), &at([0, 1, 0])));
        assert!(!map.walked(&at([0, 1, 0]), &at([1, 0, 0])));
        assert!(!map.walked(&(at([0, 0, 0]) + Vector3::y() * 0.005), &at([1, 0, 0])));
    }

    #[test]
    fn the_map_ends_where_its_lattice_does() {
        let map = map();
        let half = (SIDE as i32 - 1) / 2;
        assert!(map.slot([half, -half, half]).is_some());
        assert!(map.slot([half + 1, 0, 0]).is_none());
        assert!(map.slot([0, 0, -half - 1]).is_none());
    }
}
