//! Steady-state detection: the paper's "n consecutive samples within a sphere of radius ε" (§3).
//!
//! Read here as: n consecutive samples, all within ε of the first of them, whose mean X̄ agrees
//! within ε/10 with the mean of the n samples before them (no creep, no drift; small oscillations
//! average out). A steady state therefore takes at least 2n samples. The state machine feeds
//! samples only after the settle time since the last change (a move, a mass update, a gain
//! back-off) and resets the detector at each change.

use nalgebra::Vector3;

/// n consecutive samples within ε of the first of them, whose mean agrees within ε/10 with the
/// mean of the n samples before them (the handle is neither creeping toward its equilibrium nor
/// drifting; an oscillation much smaller than ε averages out); yields their mean.
#[derive(Clone, Debug)]
pub(crate) struct SteadyState {
    n: usize,
    eps: f64,
    /// How far two consecutive window means may differ, m.
    creep: f64,
    first: Vector3<f64>,
    sum: Vector3<f64>,
    count: usize,
    previous_mean: Option<Vector3<f64>>,
}

impl SteadyState {
    pub(crate) fn new(n: usize, eps: f64) -> Self {
        Self::with_creep(n, eps, eps / 10.0)
    }

    /// As [`SteadyState::new`], with the window means agreeing within `creep` rather than ε/10.
    pub(crate) fn with_creep(n: usize, eps: f64, creep: f64) -> Self {
        Self {
            n,
            eps,
            creep,
            first: Vector3::zeros(),
            sum: Vector3::zeros(),
            count: 0,
            previous_mean: None,
        }
    }

    /// Forget both windows.
    pub(crate) fn reset(&mut self) {
        self.count = 0;
        self.previous_mean = None;
    }
    /// Add a sample; the mean X̄ of the newest window when it completes a steady state.
    pub(crate) fn push(&mut self, x: &Vector3<f64>) -> Option<Vector3<f64>> {
        if self.count == 0 {
            self.first = *x;
            self.sum = Vector3::zeros();
        } else if (x - self.first).norm() > self.eps {
            self.first = *x;
            self.sum = Vector3::zeros();
            self.count = 0;
            self.previous_mean = None;
        }
        self.sum += x;
        self.count += 1;
        if self.count < self.n {
            return None;
        }
        let mean = self.sum / self.n as f64;
        self.count = 0;
        match self.previous_mean.replace(mean) {
            Some(previous) if (mean - previous).norm() < self.creep => Some(mean),
            _ => None,
        }
    }

    /// The newest complete window's mean, if any (steady or not).
    pub(crate) fn last_mean(&self) -> Option<Vector3<f64>> {
        self.previous_mean
    }
}

/// Changes of a reading smaller than this are no encoder step, m.
const MIN_STEP: f64 = 1e-6;

/// The position noise a device reports, from second differences: x_k − 2x_{k−1} + x_{k−2} of
/// white noise of standard deviation σ has variance 6σ², while a smooth motion (a handle still
/// settling, or ringing slowly) adds next to nothing at the report rate. Averaged over about the
/// last `window` samples. Beside it, the encoder's step: the smallest change between consecutive
/// readings seen (the largest axis's change of each; a change of less than a micrometre counts as
/// none), which a handle at rest need not show, but one coming to rest does.
#[derive(Clone, Debug)]
pub(crate) struct NoiseMeter {
    window: usize,
    previous: [Vector3<f64>; 2],
    count: usize,
    mean_square: Vector3<f64>,
    /// Smallest step seen, m (infinite: none yet).
    step: f64,
}

impl NoiseMeter {
    pub(crate) fn new(window: usize) -> Self {
        Self {
            window: window.max(1),
            previous: [Vector3::zeros(); 2],
            count: 0,
            mean_square: Vector3::zeros(),
            step: f64::INFINITY,
        }
    }

    pub(crate) fn push(&mut self, x: &Vector3<f64>) {
        if self.count >= 2 {
            let d = x - self.previous[1] * 2.0 + self.previous[0];
            let weight = 1.0 / (self.count - 1).min(self.window) as f64;
            self.mean_square += (d.component_mul(&d) - self.mean_square) * weight;
        }
        if self.count >= 1 {
            let change = (x - self.previous[1]).amax();
            if change >= MIN_STEP {
                self.step = self.step.min(change);
            }
        }
        self.previous = [self.previous[1], *x];
        self.count += 1;
    }

    /// The largest per-axis standard deviation, m.
    pub(crate) fn sigma(&self) -> f64 {
        (self.mean_square.max() / 6.0).sqrt()
    }

    /// The encoder's step, m: the smallest change between consecutive readings seen; 0 if the
    /// readings never changed by a micrometre or more.
    pub(crate) fn step(&self) -> f64 {
        if self.step.is_finite() {
            self.step
        } else {
            0.0
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn steady_state_needs_two_agreeing_windows_in_the_sphere() {
        let p = |x: f64| Vector3::new(x, 0.0, 0.0);
        let mut d = SteadyState::new(2, 1e-4);
        assert!(d.push(&p(0.0)).is_none());
        assert!(d.push(&p(2e-4)).is_none()); // leaves the sphere: restart here
        assert!(d.push(&p(2e-4)).is_none()); // first window complete: mean 2e-4
        assert!(d.push(&p(2.01e-4)).is_none());
        let mean = d.push(&p(2.01e-4)).unwrap(); // second window 2.01e-4 agrees within 1e-5
        assert!((mean.x - 2.01e-4).abs() < 1e-12);
        // A creeping handle (20 µm between window means, ε/10 = 10 µm) is not steady.
        let mut d = SteadyState::new(2, 1e-4);
        for x in [0.0, 1e-5, 2e-5, 3e-5, 4e-5, 5e-5] {
            assert!(d.push(&p(x)).is_none());
        }
        // An oscillation of ±20 µm over whole windows is.
        let mut d = SteadyState::new(4, 1e-4);
        let wave = [2e-5, -2e-5, 2e-5, -2e-5];
        assert!(wave.iter().map(|&x| d.push(&p(x))).all(|r| r.is_none()));
        assert!(wave
            .iter()
            .map(|&x| d.push(&p(x)))
            .last()
            .unwrap()
            .is_some());
    }

    #[test]
    fn the_noise_meter_sees_the_noise_and_not_a_slow_ringing() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let mut meter = NoiseMeter::new(200);
        for k in 0..2000 {
            // ±20 µm ringing at 5 Hz and uniform noise of σ = 2 µm (±2√3 µm).
            let ring = 2e-5 * (k as f64 * 1e-3 * 5.0 * std::f64::consts::TAU).sin();
            let noise = rng.gen_range(-1.0..1.0) * 2e-6 * 3f64.sqrt();
            meter.push(&Vector3::new(ring + noise, 0.0, 0.0));
        }
        assert!((meter.sigma() - 2e-6).abs() < 0.3e-6, "{}", meter.sigma());
        // Readings on a 29 µm grid flickering between two steps, while the handle creeps on.
        let mut meter = NoiseMeter::new(30);
        for k in 0..200 {
            let x = 2.9e-5 * ((k % 7 == 0) as u8 as f64) + 2.9e-5 * ((k / 50) as f64);
            meter.push(&Vector3::new(0.0, x, 0.0));
        }
        assert!((meter.step() - 2.9e-5).abs() < 1e-12, "{}", meter.step());
    }
}
