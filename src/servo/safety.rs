//! The safety layer between controller and device: limits force magnitude and rate of change,
//! turns non-finite values and faults into zero force.

use nalgebra::Vector3;

use crate::config::SafetyConfig;

/// What the safety layer did to a requested force, where the loop must count it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Limited {
    /// The request was not finite and became zero force.
    pub non_finite: bool,
}

#[derive(Clone, Debug)]
pub struct SafetyLayer {
    max_force: f64,
    /// Largest change of force per tick, N.
    max_step: f64,
    last: Vector3<f64>,
}

impl SafetyLayer {
    pub fn new(config: &SafetyConfig, period: f64) -> Self {
        Self {
            max_force: config.max_force_n,
            max_step: config.max_force_rate_n_per_s * period,
            last: Vector3::zeros(),
        }
    }

    /// The force to send for `requested`. A fault zeroes at once (never rate-limited); otherwise
    /// the magnitude is clamped, then the change since the last tick.
    pub fn limit(&mut self, requested: &Vector3<f64>, fault: bool) -> (Vector3<f64>, Limited) {
        let mut what = Limited::default();
        if fault {
            self.last = Vector3::zeros();
            return (self.last, what);
        }
        if !requested.iter().all(|c| c.is_finite()) {
            what.non_finite = true;
            self.last = Vector3::zeros();
            return (self.last, what);
        }
        let mut f = *requested;
        let magnitude = f.norm();
        if magnitude > self.max_force {
            f *= self.max_force / magnitude;
        }
        let step = f - self.last;
        let step_norm = step.norm();
        if step_norm > self.max_step {
            f = self.last + step * (self.max_step / step_norm);
        }
        self.last = f;
        (f, what)
    }

    /// Forget the last force (after a fault the next force ramps up from zero).
    pub fn reset(&mut self) {
        self.last = Vector3::zeros();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn layer() -> SafetyLayer {
        SafetyLayer::new(
            &SafetyConfig {
                max_force_n: 5.0,
                max_force_rate_n_per_s: 1000.0,
            },
            1e-3,
        )
    }

    #[test]
    fn clamps_magnitude_and_rate() {
        let mut s = layer();
        let (f, what) = s.limit(&Vector3::new(0.0, 0.0, 100.0), false);
        assert!(!what.non_finite);
        assert!((f.z - 1.0).abs() < 1e-12, "1000 N/s over 1 ms is 1 N");
        for _ in 0..10 {
            s.limit(&Vector3::new(0.0, 0.0, 100.0), false);
        }
        let (f, _) = s.limit(&Vector3::new(0.0, 0.0, 100.0), false);
        assert!((f.norm() - 5.0).abs() < 1e-12);
    }

    #[test]
    fn faults_and_nan_give_zero_at_once() {
        let mut s = layer();
        for _ in 0..10 {
            s.limit(&Vector3::new(3.0, 0.0, 0.0), false);
        }
        assert_eq!(
            s.limit(&Vector3::new(3.0, 0.0, 0.0), true).0,
            Vector3::zeros()
        );
        let (f, what) = s.limit(&Vector3::new(f64::NAN, 0.0, 0.0), false);
        assert!(what.non_finite);
        assert_eq!(f, Vector3::zeros());
    }
}
