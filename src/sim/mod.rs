//! Simulated plants: the physics behind the mock-HID device (`transport::sim`).
//!
//! A plant integrates the end-effector dynamics under the actuator force it is given; measurement
//! effects (encoder quantisation, noise) are applied by [`Encoder`] when a report is made.

use nalgebra::Vector3;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

use crate::config::SimConfig;
use crate::grid::{GridError, GridFile, MassGrid};

/// The physics of a simulated device.
pub trait Plant: Send {
    /// Integrate for `dt` seconds under the actuator force `force` (N, already limited).
    fn step(&mut self, force: &Vector3<f64>, dt: f64);
    /// True end-effector position, m.
    fn position(&self) -> Vector3<f64>;
    /// True end-effector velocity, m/s.
    fn velocity(&self) -> Vector3<f64>;
    /// The box the mechanical stops allow, m: (smallest corner, largest corner).
    fn workspace(&self) -> (Vector3<f64>, Vector3<f64>);
}

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
}

/// Position measurement: Gaussian noise then quantisation to the encoder resolution.
#[derive(Clone, Debug)]
pub struct Encoder {
    resolution: f64,
    noise: Option<Normal<f64>>,
    rng: ChaCha8Rng,
}

impl Encoder {
    /// `resolution` and `noise_std` in m (0 disables either); deterministic for a given seed.
    pub fn new(resolution: f64, noise_std: f64, seed: u64) -> Self {
        Self {
            resolution,
            noise: (noise_std > 0.0).then(|| Normal::new(0.0, noise_std).expect("finite std")),
            rng: ChaCha8Rng::seed_from_u64(seed),
        }
    }

    pub fn from_config(sim: &SimConfig) -> Self {
        Self::new(sim.encoder_resolution(), sim.noise(), sim.seed)
    }

    /// The position the device would report for the true position `x`.
    pub fn measure(&mut self, x: &Vector3<f64>) -> Vector3<f64> {
        let mut out = *x;
        if let Some(noise) = &self.noise {
            for axis in 0..3 {
                out[axis] += noise.sample(&mut self.rng);
            }
        }
        if self.resolution > 0.0 {
            out = out.map(|c| (c / self.resolution).round() * self.resolution);
        }
        out
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
        let f = p.field.gravity_force(&p.position());
        for _ in 0..10_000 {
            p.step(&f, 1e-4);
        }
        assert!(p.position().norm() < 1e-12);
    }

    #[test]
    fn encoder_quantises_and_is_deterministic() {
        let mut a = Encoder::new(5e-6, 2e-6, 7);
        let mut b = Encoder::new(5e-6, 2e-6, 7);
        let x = Vector3::new(0.0123456, -0.001, 0.0);
        for _ in 0..100 {
            let ma = a.measure(&x);
            assert_eq!(ma, b.measure(&x));
            for axis in 0..3 {
                let steps = ma[axis] / 5e-6;
                assert!((steps - steps.round()).abs() < 1e-6);
                assert!((ma[axis] - x[axis]).abs() < 2e-5);
            }
        }
    }
}
