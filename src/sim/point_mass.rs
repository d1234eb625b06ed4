//! The point-mass plant: the paper's model of a device, exact by construction.

use nalgebra::Vector3;

use super::Plant;
use crate::config::SimConfig;
use crate::grid::{GridError, GridFile, MassGrid};

/// A point-like end effector with position-dependent apparent mass:
/// M(X) Ẍ = F − M(X) g v_G − b Ẋ, inside hard stops that absorb the motion into them.
#[derive(Clone, Debug)]
pub struct PointMass {
    /// Mass field M(X) and the gravity it is subject to (g, v_G).
    pub field: MassGrid,
    /// Viscous friction b, N·s/m.
    pub damping: f64,
    /// A probe mass fixed to the end effector, kg (adds to M(X) in inertia and weight).
    pub payload: f64,
    /// Resolution of its Cartesian encoders, m (0: no quantisation).
    pub resolution: f64,
    lo: Vector3<f64>,
    hi: Vector3<f64>,
    x: Vector3<f64>,
    v: Vector3<f64>,
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
            payload: 0.0,
            resolution: 0.0,
            lo,
            hi,
            x: start.sup(&lo).inf(&hi),
            v: Vector3::zeros(),
        }
    }

    /// The plant a `[sim]` config section describes: a uniform mass, or the field of `mass_grid`.
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
        plant.resolution = sim.encoder_resolution();
        Ok(plant)
    }

    /// Apparent mass at the current position, payload included, kg (ground truth for tests).
    pub fn mass(&self) -> f64 {
        self.field.mass_at(&self.x) + self.payload
    }
}

impl Plant for PointMass {
    fn step(&mut self, force: &Vector3<f64>, dt: f64) {
        let m = self.field.mass_at(&self.x) + self.payload;
        let gravity = -self.field.gravity_direction * self.field.g;
        let a = (force - self.v * self.damping) / m + gravity;
        // Semi-implicit Euler: exact for constant acceleration up to the O(dt) start offset.
        self.v += a * dt;
        self.x += self.v * dt;
        for axis in 0..3 {
            if self.x[axis] < self.lo[axis] {
                self.x[axis] = self.lo[axis];
                self.v[axis] = self.v[axis].max(0.0);
            } else if self.x[axis] > self.hi[axis] {
                self.x[axis] = self.hi[axis];
                self.v[axis] = self.v[axis].min(0.0);
            }
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
    fn holding_force(&self) -> Vector3<f64> {
        self.field.gravity_direction * (self.mass() * self.field.g)
    }
    fn sensed_position(&self, noise: &Vector3<f64>) -> Vector3<f64> {
        let x = self.x + noise;
        if self.resolution > 0.0 {
            x.map(|c| (c / self.resolution).round() * self.resolution)
        } else {
            x
        }
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
}
