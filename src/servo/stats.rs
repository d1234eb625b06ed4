//! Timing statistics of the servo loop, kept in fixed histograms allocated before the loop starts.

use std::fmt;

/// Histogram of durations with 1 µs bins up to a limit and an overflow count.
#[derive(Clone, Debug)]
pub struct Histogram {
    bins: Box<[u32]>,
    overflow: u64,
    count: u64,
    max_ns: u64,
}

impl Histogram {
    /// Room for durations up to `limit_us` µs at 1 µs resolution.
    pub fn new(limit_us: usize) -> Self {
        Self {
            bins: vec![0; limit_us].into_boxed_slice(),
            overflow: 0,
            count: 0,
            max_ns: 0,
        }
    }

    pub fn record_ns(&mut self, ns: u64) {
        self.count += 1;
        self.max_ns = self.max_ns.max(ns);
        match self.bins.get_mut((ns / 1000) as usize) {
            Some(bin) => *bin = bin.saturating_add(1),
            None => self.overflow += 1,
        }
    }

    pub fn count(&self) -> u64 {
        self.count
    }

    /// Largest recorded value, µs.
    pub fn max_us(&self) -> f64 {
        self.max_ns as f64 / 1000.0
    }

    /// The `p`-quantile (0–1), µs, to bin resolution (upper edge of its bin); None when empty.
    pub fn quantile_us(&self, p: f64) -> Option<f64> {
        if self.count == 0 {
            return None;
        }
        let rank = ((p * self.count as f64).ceil() as u64).clamp(1, self.count);
        let mut seen = 0u64;
        for (i, &n) in self.bins.iter().enumerate() {
            seen += u64::from(n);
            if seen >= rank {
                return Some((i + 1) as f64);
            }
        }
        Some(self.max_us())
    }
}

/// Everything the loop counts about its own timing.
#[derive(Clone, Debug)]
pub struct TimingStats {
    /// Nominal period, s.
    pub nominal_period: f64,
    /// Intervals between consecutive input reports on the transport's clock.
    pub period: Histogram,
    /// Time from receiving a report to having handed the output report over (wall clock).
    pub compute: Histogram,
    pub ticks: u64,
    /// Reports that came more than 1.5 periods after the previous one.
    pub late: u64,
    /// Reports the loop never saw (gaps in the device's sequence numbers).
    pub missed: u64,
    /// Ticks after which the loop skipped ahead over missed reports.
    pub overruns: u64,
    /// Reports that failed to decode.
    pub garbled: u64,
    /// Times the deadline watchdog fired.
    pub watchdog_faults: u64,
    /// Ticks on which the device reported a fault.
    pub device_fault_ticks: u64,
    /// Ticks whose controller force was not finite.
    pub non_finite_forces: u64,
}

impl TimingStats {
    pub fn new(nominal_period: f64) -> Self {
        Self {
            nominal_period,
            period: Histogram::new(20_000),
            compute: Histogram::new(5_000),
            ticks: 0,
            late: 0,
            missed: 0,
            overruns: 0,
            garbled: 0,
            watchdog_faults: 0,
            device_fault_ticks: 0,
            non_finite_forces: 0,
        }
    }

    /// Record the interval between two reports, s.
    pub fn record_period(&mut self, dt: f64) {
        self.period.record_ns((dt.max(0.0) * 1e9) as u64);
        if dt > 1.5 * self.nominal_period {
            self.late += 1;
        }
    }
}

impl fmt::Display for TimingStats {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let q = |h: &Histogram, p: f64| h.quantile_us(p).map_or("-".into(), |v| format!("{v:.0}"));
        writeln!(
            f,
            "servo loop: {} ticks at nominal {:.0} Hz",
            self.ticks,
            1.0 / self.nominal_period
        )?;
        writeln!(
            f,
            "  period µs     p50 {}  p99 {}  p99.9 {}  max {:.0}",
            q(&self.period, 0.5),
            q(&self.period, 0.99),
            q(&self.period, 0.999),
            self.period.max_us()
        )?;
        writeln!(
            f,
            "  tick compute µs  p50 {}  p99 {}  max {:.1}",
            q(&self.compute, 0.5),
            q(&self.compute, 0.99),
            self.compute.max_us()
        )?;
        write!(
            f,
            "  late {}  missed {}  overruns {}  garbled {}  watchdog faults {}  device-fault ticks {}  non-finite forces {}",
            self.late,
            self.missed,
            self.overruns,
            self.garbled,
            self.watchdog_faults,
            self.device_fault_ticks,
            self.non_finite_forces
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantiles_of_a_known_distribution() {
        let mut h = Histogram::new(100);
        for us in 0..100u64 {
            h.record_ns(us * 1000 + 500);
        }
        assert_eq!(h.quantile_us(0.5), Some(50.0));
        assert_eq!(h.quantile_us(0.99), Some(99.0));
        h.record_ns(1_000_000);
        assert_eq!(h.quantile_us(1.0), Some(1000.0));
    }
}
