//! Exploration of a workspace of unknown shape (`calibration.workspace = "explore"`): after the
//! initialisation, the hold drives the handle from X_C outward along 26 directions (the faces,
//! edges and corners of a cube) at [`PROBE_SPEED`] until it meets a mechanical stop or an
//! obstacle, then glides back to X_C. The contacts make a star-shaped [`WorkspaceMap`] around
//! X_C, and the grid is planned on the vertices it holds with a margin
//! ([`GridPlan::explored`](super::GridPlan::explored)).
//!
//! A stop is met when the handle stops following the reference while the hold's force grows:
//! the reference runs ahead of the handle along the probe by more than [`CONTACT_LAG`] (or by
//! what half the push limit stretches the hold by, if that is less). The probe's speed is the
//! handle's speed when it meets the stop, so no stop is struck faster than
//! [`CONTACT_SPEED`]. A probe that reaches the configured box (`device.workspace_*_mm`) ends
//! there without contact: exploration never leaves the box the user allowed.

use nalgebra::Vector3;

use super::machine::Glide;
use crate::control::pd::AxisGains;
use crate::control::DeviceState;

/// Probes run: one per direction of [`directions`].
pub const PROBES: usize = 26;
/// Speed of the reference along a probe, m/s: the speed the handle meets a stop at.
pub const PROBE_SPEED: f64 = 0.015;
/// The bound on the handle's speed at any contact during exploration, m/s (documented; the
/// tests read the plant's contact log against it).
pub const CONTACT_SPEED: f64 = 0.020;
/// Time constant of the probe's speed ramp from rest, s.
const PROBE_RAMP: f64 = 0.2;
/// How far the reference may run ahead of the handle along a probe before it counts as a stop,
/// m.
pub const CONTACT_LAG: f64 = 0.003;
/// Share of the push limit the hold may push a stop with before it counts as met.
const CONTACT_PUSH_SHARE: f64 = 0.5;
/// Peak speed of the glide back to X_C, m/s: no faster than a probe, as the straight line back
/// may cross a stop the probe slid along on its way out.
const RETURN_SPEED: f64 = PROBE_SPEED;
/// Shortest glide back, s, and the hold at X_C before the next probe, s.
const MIN_RETURN: f64 = 0.5;
const HOLD_AT_CENTRE: f64 = 0.3;
/// Integral time of the hold's integral term, s: it takes up the change of the holding force
/// along the probe (the hold's gravity term is the load at X_C).
const INTEGRAL_TIME: f64 = 1.0;
/// Distance kept from the explored boundary by every vertex calibrated, m: a vertex's strokes
/// reach 4 mm from it and its band pushes a millimetre or two.
pub const MARGIN: f64 = 0.012;
/// A probe informs the reach within this angle of it (cos 45°).
const WINDOW_COS: f64 = std::f64::consts::FRAC_1_SQRT_2;

/// One probe's end: the direction from X_C to where the handle came to a stop (off the probe's
/// line if it slid along a stop oblique to it), how far from X_C that is, and whether it met a
/// stop (false: it reached the configured box).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ray {
    pub direction: Vector3<f64>,
    /// m.
    pub reach: f64,
    pub stopped: bool,
}

/// The reachable workspace as exploration found it: star-shaped around X_C, its reach along any
/// direction interpolated between the probes within 45° of it, inside the configured box.
#[derive(Clone, Debug, PartialEq)]
pub struct WorkspaceMap {
    pub centre: Vector3<f64>,
    pub rays: Vec<Ray>,
    /// The configured box (`device.workspace_*_mm`), m.
    pub bounds: (Vector3<f64>, Vector3<f64>),
}

impl WorkspaceMap {
    /// The reach along unit `u`, m: the shortest reach of the probes within 45° of it. It never
    /// lies beyond a flat stop or wall any of them met (a probe at an angle to a wall meets it
    /// farther out than the wall's nearest point, never nearer), at the cost of the corners of
    /// a workspace that bulges between probes.
    pub fn reach(&self, u: &Vector3<f64>) -> f64 {
        self.rays
            .iter()
            .filter(|ray| u.dot(&ray.direction) > WINDOW_COS)
            .map(|ray| ray.reach)
            .reduce(f64::min)
            .unwrap_or(0.0)
    }

    /// Whether `x` lies at least `margin` (m) inside the explored workspace and the box.
    pub fn contains(&self, x: &Vector3<f64>, margin: f64) -> bool {
        let (lo, hi) = self.bounds;
        if (0..3).any(|a| x[a] < lo[a] + margin || x[a] > hi[a] - margin) {
            return false;
        }
        let d = x - self.centre;
        let r = d.norm();
        r < 1e-9 || r <= self.reach(&(d / r)) - margin
    }

    /// The box around every point the probes reached, m.
    pub fn extent(&self) -> (Vector3<f64>, Vector3<f64>) {
        self.rays
            .iter()
            .fold((self.centre, self.centre), |(lo, hi), ray| {
                let x = self.centre + ray.direction * ray.reach;
                (lo.inf(&x), hi.sup(&x))
            })
    }
}

/// The 26 probe directions: (i, j, k) ∈ {−1, 0, 1}³ without the origin, normalised.
pub fn directions() -> impl Iterator<Item = Vector3<f64>> {
    (0..27).filter(|&n| n != 13).map(|n| {
        Vector3::new(
            (n % 3) as f64 - 1.0,
            ((n / 3) % 3) as f64 - 1.0,
            (n / 9) as f64 - 1.0,
        )
        .normalize()
    })
}

/// The leg of the probe in progress.
#[derive(Clone, Copy, Debug)]
enum Leg {
    /// Outward from X_C since `start`, at most `length` m (to the box).
    Out { start: f64, length: f64 },
    /// The glide back to X_C, then a short hold there.
    Back(Glide),
}

/// Runs the probes (module docs). Built off the servo thread; [`Explorer::tick`] does not
/// allocate.
#[derive(Clone, Debug)]
pub struct Explorer {
    map: WorkspaceMap,
    /// Probes still to run, in order.
    directions: [Vector3<f64>; PROBES],
    leg: Leg,
    /// The hold's integral term, N, and the time of the last tick, s.
    integral: Vector3<f64>,
    last_time: f64,
    /// The most the integral term and the probe's push may add to the load, N.
    push_limit: f64,
}

impl Explorer {
    /// Probes inside `bounds` (m); `push_limit` is the most calibration pushes beyond the forces
    /// it holds, N. [`Explorer::begin`] starts them.
    pub fn new(bounds: (Vector3<f64>, Vector3<f64>), push_limit: f64) -> Self {
        let mut probes = [Vector3::zeros(); PROBES];
        for (slot, d) in probes.iter_mut().zip(directions()) {
            *slot = d;
        }
        Self {
            map: WorkspaceMap {
                centre: Vector3::zeros(),
                rays: Vec::with_capacity(probes.len()),
                bounds,
            },
            directions: probes,
            leg: Leg::Out {
                start: 0.0,
                length: 0.0,
            },
            integral: Vector3::zeros(),
            last_time: 0.0,
            push_limit,
        }
    }

    /// Start the probes from `centre` (m, the handle at rest there) at time `t`, forgetting any
    /// earlier ones.
    pub fn begin(&mut self, centre: Vector3<f64>, t: f64) {
        self.map.centre = centre;
        self.map.rays.clear();
        self.integral = Vector3::zeros();
        self.last_time = t;
        self.start_probe(t);
    }

    /// The map so far (complete once [`Explorer::tick`] has returned `None`).
    pub fn map(&self) -> &WorkspaceMap {
        &self.map
    }

    /// Set off along the next direction at time `t`.
    fn start_probe(&mut self, t: f64) {
        let d = self.directions[self.map.rays.len()];
        self.leg = Leg::Out {
            start: t,
            length: box_exit(&self.map.centre, &d, &self.map.bounds),
        };
    }

    /// The hold's force this tick with the hold's `gains` and the load at X_C `load`; `None` once
    /// every probe is done (the handle is back at X_C).
    pub fn tick(
        &mut self,
        s: &DeviceState,
        gains: &AxisGains,
        load: &Vector3<f64>,
    ) -> Option<Vector3<f64>> {
        let dt = (s.time - self.last_time).max(0.0);
        self.last_time = s.time;
        let centre = self.map.centre;
        let (target, velocity) = match self.leg {
            Leg::Out { start, length } => {
                let d = self.directions[self.map.rays.len()];
                let tau = (s.time - start).max(0.0);
                let ramp = 1.0 - (-tau / PROBE_RAMP).exp();
                let along = PROBE_SPEED * (tau - PROBE_RAMP * ramp);
                let target = centre + d * along.min(length);
                // The whole tracking error, not only its part along the probe: a handle turned
                // aside by a stop oblique to the probe is held there too, and is not pulled
                // along the stop towards a reference that runs on.
                let lag = (target - s.position).norm();
                let stiffest = gains.stiffness.max();
                let lag_limit = CONTACT_LAG.min(CONTACT_PUSH_SHARE * self.push_limit / stiffest);
                if lag > lag_limit || along >= length {
                    // Where the handle is, not its projection on the probe: it may have slid
                    // along a stop oblique to the probe before the lag grew, and the point it
                    // rests at is the one known to be on the workspace's boundary.
                    let reached = s.position - centre;
                    let reach = reached.norm();
                    self.map.rays.push(Ray {
                        direction: if reach > 1e-9 { reached / reach } else { d },
                        reach,
                        stopped: along < length,
                    });
                    self.leg = Leg::Back(Glide {
                        from: s.position,
                        to: centre,
                        start: s.time,
                        duration: (1.875 * reach / RETURN_SPEED).max(MIN_RETURN),
                    });
                    (s.position, Vector3::zeros())
                } else {
                    (target, d * PROBE_SPEED * ramp)
                }
            }
            Leg::Back(glide) => {
                if glide.progress(s.time) >= 1.0 + HOLD_AT_CENTRE / glide.duration {
                    if self.map.rays.len() == self.directions.len() {
                        return None;
                    }
                    self.start_probe(s.time);
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
}

/// How far from `centre` along unit `d` the box `bounds` ends, m.
fn box_exit(centre: &Vector3<f64>, d: &Vector3<f64>, bounds: &(Vector3<f64>, Vector3<f64>)) -> f64 {
    let (lo, hi) = bounds;
    (0..3)
        .filter(|&a| d[a].abs() > 1e-12)
        .map(|a| {
            let wall = if d[a] > 0.0 { hi[a] } else { lo[a] };
            ((wall - centre[a]) / d[a]).max(0.0)
        })
        .fold(f64::INFINITY, f64::min)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sphere(radius: f64) -> WorkspaceMap {
        WorkspaceMap {
            centre: Vector3::zeros(),
            rays: directions()
                .map(|direction| Ray {
                    direction,
                    reach: radius,
                    stopped: true,
                })
                .collect(),
            bounds: (Vector3::repeat(-1.0), Vector3::repeat(1.0)),
        }
    }

    #[test]
    fn twenty_six_unit_directions_cover_every_direction_within_45_degrees() {
        let d: Vec<_> = directions().collect();
        assert_eq!(d.len(), 26);
        assert!(d.iter().all(|u| (u.norm() - 1.0).abs() < 1e-12));
        // Every direction has a probe closer than 45° (the worst lies between a face, an edge
        // and a corner direction).
        for i in 0..20 {
            for j in 0..40 {
                let (th, ph) = (
                    std::f64::consts::PI * (i as f64 + 0.5) / 20.0,
                    0.157 * j as f64,
                );
                let u = Vector3::new(th.sin() * ph.cos(), th.sin() * ph.sin(), th.cos());
                let best = d.iter().map(|v| v.dot(&u)).fold(f64::MIN, f64::max);
                assert!(best > WINDOW_COS + 0.1, "{u:?}: {best}");
            }
        }
    }

    #[test]
    fn a_map_of_equal_reaches_is_a_ball_less_its_margin() {
        let map = sphere(0.1);
        let u = Vector3::new(0.3, -0.5, 0.8).normalize();
        assert!((map.reach(&u) - 0.1).abs() < 1e-12);
        assert!(map.contains(&(u * 0.087), 0.012));
        assert!(!map.contains(&(u * 0.089), 0.012));
        assert!(map.contains(&Vector3::zeros(), 0.012));
    }

    #[test]
    fn a_short_probe_shrinks_the_map_around_it_only() {
        let mut map = sphere(0.1);
        let up = Vector3::z();
        for ray in &mut map.rays {
            if ray.direction == up {
                ray.reach = 0.03;
            }
        }
        assert!(map.reach(&up) < 0.031);
        assert!(!map.contains(&Vector3::new(0.0, 0.0, 0.05), 0.012));
        assert!(map.contains(&Vector3::new(0.0, 0.0, -0.08), 0.012));
        assert!(map.contains(&Vector3::new(0.08, 0.0, 0.0), 0.012));
    }

    #[test]
    fn the_box_bounds_the_map_and_ends_a_probe() {
        let mut map = sphere(0.5);
        map.bounds = (Vector3::repeat(-0.05), Vector3::repeat(0.05));
        assert!(!map.contains(&Vector3::new(0.045, 0.0, 0.0), 0.012));
        assert!(map.contains(&Vector3::new(0.035, 0.0, 0.0), 0.012));
        let d = Vector3::new(1.0, 1.0, 0.0).normalize();
        let exit = box_exit(&Vector3::zeros(), &d, &map.bounds);
        assert!((exit - 0.05 * 2f64.sqrt()).abs() < 1e-12);
    }
}
