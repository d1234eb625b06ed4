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
pub(super) struct SteadyState {
    n: usize,
    eps: f64,
    first: Vector3<f64>,
    sum: Vector3<f64>,
    count: usize,
    previous_mean: Option<Vector3<f64>>,
}

impl SteadyState {
    pub(super) fn new(n: usize, eps: f64) -> Self {
        Self {
            n,
            eps,
            first: Vector3::zeros(),
            sum: Vector3::zeros(),
            count: 0,
            previous_mean: None,
        }
    }
    /// Forget both windows.
    pub(super) fn reset(&mut self) {
        self.count = 0;
        self.previous_mean = None;
    }
    /// Add a sample; the mean X̄ of the newest window when it completes a steady state.
    pub(super) fn push(&mut self, x: &Vector3<f64>) -> Option<Vector3<f64>> {
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
            Some(previous) if (mean - previous).norm() < self.eps / 10.0 => Some(mean),
            _ => None,
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
}
