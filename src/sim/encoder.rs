//! Position measurement as a device makes it: noise at the handle, then the plant's own sensors.

use nalgebra::Vector3;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

use super::Plant;
use crate::config::SimConfig;

/// Position measurement: Gaussian noise at the handle, then quantisation by the plant's encoders
/// ([`Plant::sensed_position`]).
#[derive(Clone, Debug)]
pub struct Encoder {
    noise: Option<Normal<f64>>,
    rng: ChaCha8Rng,
}

impl Encoder {
    /// `noise_std` in m (0 disables noise); deterministic for a given seed.
    pub fn new(noise_std: f64, seed: u64) -> Self {
        Self {
            noise: (noise_std > 0.0).then(|| Normal::new(0.0, noise_std).expect("finite std")),
            rng: ChaCha8Rng::seed_from_u64(seed),
        }
    }

    pub fn from_config(sim: &SimConfig) -> Self {
        Self::new(sim.noise(), sim.seed)
    }

    /// The position the device reports for the state of `plant`.
    pub fn measure(&mut self, plant: &dyn Plant) -> Vector3<f64> {
        plant.sensed_position(&self.sample_noise())
    }

    /// The next displacement of the handle as its sensors see it, m.
    pub fn sample_noise(&mut self) -> Vector3<f64> {
        let mut noise = Vector3::zeros();
        if let Some(n) = &self.noise {
            for axis in 0..3 {
                noise[axis] = n.sample(&mut self.rng);
            }
        }
        noise
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::PointMass;

    #[test]
    fn encoder_quantises_and_is_deterministic() {
        let mut plant = PointMass::from_config(&SimConfig::default()).unwrap();
        plant.resolution = 5e-6;
        let mut a = Encoder::new(2e-6, 7);
        let mut b = Encoder::new(2e-6, 7);
        for _ in 0..100 {
            let ma = a.measure(&plant);
            assert_eq!(ma, b.measure(&plant));
            for axis in 0..3 {
                let steps = ma[axis] / 5e-6;
                assert!((steps - steps.round()).abs() < 1e-6);
                assert!((ma[axis] - plant.position()[axis]).abs() < 2e-5);
            }
        }
    }
}
