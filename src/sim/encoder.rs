//! Position measurement as a device's encoders make it.

use nalgebra::Vector3;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

use crate::config::SimConfig;

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
