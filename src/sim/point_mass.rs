//! The point-mass plant: the paper's model of a device, exact by construction.

use nalgebra::Vector3;

use super::{ContactLog, Plant};
use crate::config::SimConfig;
use crate::grid::{GridError, GridFile, MassGrid};

/// Inertia used when none is given and the apparent mass is (nearly) zero, kg.
const MIN_INERTIA: f64 = 1e-3;

/// A point-like end effector with position-dependent apparent mass M(X) and inertia m:
/// m Ẍ = F − M(X) g v_G − b Ẋ − k (X − X_k) + F_c, inside hard stops that absorb the motion into
/// them (k, X_k: an optional spring, a cable pulling the handle).
///
/// F_c is Coulomb friction of level f_c: while the handle is at rest it sticks as long as the
/// net force on it, |F − M g v_G|, is at most f_c (F_c cancels it); otherwise it slides and
/// F_c = −f_c Ẋ/|Ẋ|. M may be negative or zero: an over-balanced handle whose counterweight
/// pushes it along v_G. The inertia m is positive whatever M is.
#[derive(Clone, Debug)]
pub struct PointMass {
    /// Mass field M(X) and the gravity it is subject to (g, v_G).
    pub field: MassGrid,
    /// Viscous friction b, N·s/m.
    pub damping: f64,
    /// Coulomb friction level f_c, N (static and sliding alike).
    pub friction: f64,
    /// Spring stiffness k, N/m, and its anchor X_k, m.
    pub spring: f64,
    pub spring_anchor: Vector3<f64>,
    /// Moving mass m without the payload, kg; `None`: |M(X)| (at least 1 g).
    pub inertia: Option<f64>,
    /// A box inside the workspace the handle cannot enter (smallest corner, largest), m: an
    /// obstacle, stopping the handle on the face it reaches.
    pub obstacle: Option<(Vector3<f64>, Vector3<f64>)>,
    /// A probe mass fixed to the end effector, kg (adds to M(X) in weight and to the inertia).
    pub payload: f64,
    /// Resolution of its Cartesian encoders, m (0: no quantisation).
    pub resolution: f64,
    lo: Vector3<f64>,
    hi: Vector3<f64>,
    x: Vector3<f64>,
    v: Vector3<f64>,
    contacts: ContactLog,
}

impl PointMass {
    pub fn new(
        field: MassGrid,
        damping: f64,
        workspace: (Vector3<f64>, Vector3<f64>),
        start: Vector3<f64>,
    ) -> Self {
        let (lo, hi) = workspace;
        Self {
            field,
            damping,
            friction: 0.0,
            spring: 0.0,
            spring_anchor: Vector3::zeros(),
            inertia: None,
            obstacle: None,
            payload: 0.0,
            resolution: 0.0,
            lo,
            hi,
            x: start.sup(&lo).inf(&hi),
            v: Vector3::zeros(),
            contacts: ContactLog::default(),
        }
    }

    /// The plant a `[sim]` config section describes: a uniform mass, or the field of `mass_grid`.
    ///
    /// # Errors
    /// The [`GridError`] of a `mass_grid` that does not load.
    pub fn from_config(sim: &SimConfig) -> Result<Self, GridError> {
        let (lo, hi) = sim.workspace();
        let field = match &sim.mass_grid {
            Some(path) => GridFile::load(path)?.grid,
            None => MassGrid::uniform(
                sim.mass_kg,
                sim.g,
                Vector3::from(sim.gravity_direction),
                lo,
                (hi - lo).max(),
                [2, 2, 2],
            ),
        };
        let mut plant = Self::new(field, sim.damping_n_s_per_m, (lo, hi), sim.start_position());
        plant.payload = sim.probe_mass_kg;
        plant.friction = sim.coulomb_friction_n;
        plant.spring = sim.spring_n_per_m;
        plant.spring_anchor = sim.spring_anchor();
        plant.inertia = sim.inertia_kg;
        plant.obstacle = sim.obstacle();
        plant.resolution = sim.encoder_resolution();
        Ok(plant)
    }

    /// Apparent mass at the current position, payload included, kg (ground truth for tests).
    pub fn mass(&self) -> f64 {
        self.field.mass_at(&self.x) + self.payload
    }

    /// Moving mass at the current position, payload included, kg.
    pub fn moving_mass(&self) -> f64 {
        let own = self
            .inertia
            .unwrap_or_else(|| self.field.mass_at(&self.x).abs().max(MIN_INERTIA));
        own + self.payload
    }
}

impl Plant for PointMass {
    /// Semi-implicit Euler with the friction impulse applied implicitly: the velocity the other
    /// forces would give, v', loses f_c dt / m along itself, and becomes zero when that is more
    /// than |v'| (the handle stops, or stays stuck: from rest, exactly when |net force| ≤ f_c).
    fn step(&mut self, force: &Vector3<f64>, dt: f64) {
        let m = self.moving_mass();
        let net = force - self.holding_force() - self.v * self.damping;
        let trial = self.v + net * (dt / m);
        let braking = self.friction * dt / m;
        let speed = trial.norm();
        self.v = if speed <= braking {
            Vector3::zeros()
        } else {
            trial * (1.0 - braking / speed)
        };
        let before = self.x;
        let moving = self.v;
        self.x += self.v * dt;
        self.contacts.tick(dt);
        // A contact: the step ends on a face or a stop the handle was not resting on before. Its
        // speed is the velocity the face absorbs (the handle slides on along it).
        let mut met = false;
        if let Some((lo, hi)) = self.obstacle {
            let inside = (0..3).all(|a| self.x[a] > lo[a] && self.x[a] < hi[a]);
            // Entering the box, the handle stops on the face it crossed: of the axes it was
            // outside the box along before the step, the one it went least deep along.
            let crossed = (0..3)
                .filter(|&a| before[a] <= lo[a] || before[a] >= hi[a])
                .min_by(|&a, &b| {
                    let depth = |k: usize| (self.x[k] - lo[k]).min(hi[k] - self.x[k]);
                    depth(a).total_cmp(&depth(b))
                });
            if let (true, Some(a)) = (inside, crossed) {
                self.x[a] = if before[a] <= lo[a] { lo[a] } else { hi[a] };
                self.v[a] = 0.0;
                met |= before[a] != self.x[a];
            }
        }
        for axis in 0..3 {
            if self.x[axis] < self.lo[axis] {
                self.x[axis] = self.lo[axis];
                self.v[axis] = self.v[axis].max(0.0);
                met |= before[axis] != self.lo[axis];
            } else if self.x[axis] > self.hi[axis] {
                self.x[axis] = self.hi[axis];
                self.v[axis] = self.v[axis].min(0.0);
                met |= before[axis] != self.hi[axis];
            }
        }
        if met {
            self.contacts.record(self.x, (moving - self.v).norm());
        }
    }
    fn position(&self) -> Vector3<f64> {
        self.x
    }
    fn velocity(&self) -> Vector3<f64> {
        self.v
    }
    fn workspace(&self) -> (Vector3<f64>, Vector3<f64>) {
        (self.lo, self.hi)
    }
    fn contacts(&self) -> &ContactLog {
        &self.contacts
    }
    fn holding_force(&self) -> Vector3<f64> {
        self.field.gravity_direction * (self.mass() * self.field.g)
            + (self.x - self.spring_anchor) * self.spring
    }
    fn moving_mass_per_axis(&self) -> Vector3<f64> {
        Vector3::repeat(self.moving_mass())
    }
    fn up(&self) -> Vector3<f64> {
        self.field.gravity_direction
    }
    fn sensed_position(&self, noise: &Vector3<f64>) -> Vector3<f64> {
        let x = self.x + noise;
        if self.resolution > 0.0 {
            x.map(|c| (c / self.resolution).round() * self.resolution)
        } else {
            x
        }
    }

    fn set_world(&mut self, payload_kg: f64, up: &Vector3<f64>) {
        self.payload = payload_kg;
        self.field.gravity_direction = *up;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn free_fall_follows_g_along_minus_v_g_and_stops_at_the_floor() {
        let sim = SimConfig {
            gravity_direction: [0.0, 0.1, 1.0],
            ..SimConfig::default()
        };
        let mut p = PointMass::from_config(&sim).unwrap();
        let dt = 1e-4;
        for _ in 0..1000 {
            p.step(&Vector3::zeros(), dt);
        }
        let v_g = Vector3::new(0.0, 0.1, 1.0).normalize();
        // After 0.1 s: v = −g t v_G exactly with semi-implicit Euler.
        assert!((p.velocity() + v_g * 9.81 * 0.1).norm() < 1e-9);
        for _ in 0..100_000 {
            p.step(&Vector3::zeros(), dt);
        }
        assert!((p.position().z - (-0.08)).abs() < 1e-12);
        assert!(p.velocity().norm() < 1e-9);
    }

    #[test]
    fn exact_gravity_force_holds_the_mass_still() {
        let mut p = PointMass::from_config(&SimConfig::default()).unwrap();
        let f = p.holding_force();
        assert_eq!(f, p.field.gravity_force(&p.position()));
        for _ in 0..10_000 {
            p.step(&f, 1e-4);
        }
        assert!(p.position().norm() < 1e-12);
    }

    /// A uniform frictional point mass at rest at the origin, gravity along −z, far from stops.
    fn frictional(mass: f64, inertia: Option<f64>, friction: f64) -> PointMass {
        let sim = SimConfig {
            mass_kg: mass,
            inertia_kg: inertia,
            coulomb_friction_n: friction,
            noise_mm: 0.0,
            ..SimConfig::default()
        };
        PointMass::from_config(&sim).unwrap()
    }

    #[test]
    fn a_handle_sticks_while_the_net_force_is_inside_the_friction_band() {
        let mut p = frictional(0.12, None, 0.1);
        let hold = p.holding_force();
        // 0.099 N of net force, in any direction: stuck for a whole second.
        for dir in [
            Vector3::x(),
            -Vector3::z(),
            Vector3::new(1.0, -1.0, 1.0).normalize(),
        ] {
            for _ in 0..10_000 {
                p.step(&(hold + dir * 0.099), 1e-4);
            }
            assert_eq!(p.position(), Vector3::zeros(), "{dir}");
            assert_eq!(p.velocity(), Vector3::zeros());
        }
        // Without any actuator force the 1.18 N weight is far outside the band: it falls, at
        // (M g − f_c) / m.
        let mut p = frictional(0.12, None, 0.1);
        for _ in 0..1000 {
            p.step(&Vector3::zeros(), 1e-4);
        }
        let a = (0.12 * 9.81 - 0.1) / 0.12;
        assert!((p.velocity().z + a * 0.1).abs() < 1e-9, "{}", p.velocity());
    }

    #[test]
    fn past_the_band_it_slides_against_the_friction_and_stops_without_turning_back() {
        let mut p = frictional(0.12, None, 0.1);
        let hold = p.holding_force();
        // 0.13 N along x: 0.03 N beyond the band accelerates the 0.12 kg handle at 0.25 m/s².
        let dt = 1e-4;
        for _ in 0..2000 {
            p.step(&(hold + Vector3::x() * 0.13), dt);
        }
        let (x, v) = (p.position(), p.velocity());
        assert!((v.x - 0.25 * 0.2).abs() < 1e-9, "{v}");
        // Semi-implicit Euler: x = a dt² n(n+1)/2.
        assert!(
            (x.x - 0.25 * dt * dt * 2000.0 * 2001.0 / 2.0).abs() < 1e-12,
            "{x}"
        );
        assert!(x.y.abs() < 1e-15 && x.z.abs() < 1e-15, "{x}");
        // Released to the holding force alone, friction brakes it at f_c / m = 0.833 m/s²: it
        // stops after 0.06 s, 1.5 mm on, and stays there.
        let mut stopped_at = None;
        for n in 0..20_000 {
            p.step(&hold, dt);
            if stopped_at.is_none() && p.velocity() == Vector3::zeros() {
                stopped_at = Some((n + 1) as f64 * dt);
            }
        }
        let t = stopped_at.unwrap();
        assert!((t - 0.05 / (0.1 / 0.12)).abs() < 2.0 * dt, "{t} s");
        assert!((p.position().x - x.x - 0.05 * 0.05 / (2.0 * 0.1 / 0.12)).abs() < 1e-5);
        assert_eq!(p.velocity(), Vector3::zeros());
    }

    #[test]
    fn an_over_balanced_handle_rises_and_its_holding_force_points_down() {
        // −8 g apparent mass on 50 g of moving mass: released, it rises at 8/50 g.
        let mut p = frictional(-0.008, Some(0.05), 0.0);
        let hold = p.holding_force();
        assert!(
            (hold - Vector3::new(0.0, 0.0, -0.008 * 9.81)).norm() < 1e-12,
            "{hold}"
        );
        for _ in 0..1000 {
            p.step(&Vector3::zeros(), 1e-4);
        }
        assert!((p.velocity().z - 0.008 / 0.05 * 9.81 * 0.1).abs() < 1e-9);
        // Its holding force keeps it still; with friction as large as the load, so does nothing.
        let mut p = frictional(-0.008, Some(0.05), 0.08);
        for _ in 0..10_000 {
            p.step(&Vector3::zeros(), 1e-4);
        }
        assert_eq!(p.position(), Vector3::zeros());
        // A weightless handle stays where it is, whatever its inertia.
        let mut p = frictional(0.0, None, 0.0);
        assert_eq!(p.moving_mass(), MIN_INERTIA);
        for _ in 0..10_000 {
            p.step(&Vector3::zeros(), 1e-4);
        }
        assert_eq!(p.position(), Vector3::zeros());
    }

    #[test]
    fn cartesian_encoders_quantise_to_their_resolution() {
        let mut p = PointMass::from_config(&SimConfig::default()).unwrap();
        p.resolution = 5e-6;
        p.x = Vector3::new(0.0123456, -0.001, 0.0);
        let m = p.sensed_position(&Vector3::new(1e-6, 0.0, -4e-6));
        for axis in 0..3 {
            let steps = m[axis] / 5e-6;
            assert!((steps - steps.round()).abs() < 1e-6);
        }
        assert!((m - Vector3::new(0.012345, -0.001, -0.000005)).amax() < 1e-12);
    }

    #[test]
    fn an_obstacle_stops_the_handle_on_the_face_it_reaches() {
        // A 0.12 kg handle falls onto a box below it, and slides along x into the side of
        // another.
        let mut p = frictional(0.12, None, 0.0);
        p.obstacle = Some((
            Vector3::new(-0.01, -0.01, -0.03),
            Vector3::new(0.01, 0.01, -0.02),
        ));
        for _ in 0..10_000 {
            p.step(&Vector3::zeros(), 1e-4);
        }
        assert!((p.position() - Vector3::new(0.0, 0.0, -0.02)).norm() < 1e-12);
        // One contact, logged when it landed (resting on the face is no new one).
        assert_eq!(p.contacts().count(), 1);
        assert!(p.contacts().fastest() > 0.1);
        let mut p = frictional(0.12, None, 0.0);
        p.obstacle = Some((
            Vector3::new(0.005, -0.01, -0.01),
            Vector3::new(0.02, 0.01, 0.01),
        ));
        let push = p.holding_force() + Vector3::new(0.5, 0.0, 0.0);
        for _ in 0..10_000 {
            p.step(&push, 1e-4);
        }
        assert!((p.position() - Vector3::new(0.005, 0.0, 0.0)).norm() < 1e-12);
        assert_eq!(p.velocity().x, 0.0);
        assert_eq!(p.contacts().count(), 1);
        assert_eq!(p.contacts().contacts()[0].position, p.position());
    }
}
