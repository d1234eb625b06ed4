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

    /// The `p`-quantile (0–1), µs, to bin resolution (upper edge of its bin, but never above the
    /// largest value recorded); None when empty.
    pub fn quantile_us(&self, p: f64) -> Option<f64> {
        if self.count == 0 {
            return None;
        }
        let rank = ((p * self.count as f64).ceil() as u64).clamp(1, self.count);
        let mut seen = 0u64;
        for (i, &n) in self.bins.iter().enumerate() {
            seen += u64::from(n);
            if seen >= rank {
                return Some(((i + 1) as f64).min(self.max_us()));
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
    /// Lateness of each report: host receive time minus device timestamp, less the smallest such
    /// difference seen (see [`TimingStats::record_lateness`]). On a simulated device the
    /// timestamp is the report's absolute deadline, so this is lateness against the deadline.
    pub lateness: Histogram,
    pub ticks: u64,
    /// Reports that came more than 1.5 periods after the previous one.
    pub late: u64,
    /// Reports received more than one period after their timestamp said they were due.
    pub late_wakeups: u64,
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
    /// Reports whose device clock stepped back (a device reset, or a broken clock).
    pub clock_jumps_back: u64,
    /// How fast the device clock may run slow against the host's, as a fraction: the floor of
    /// the clock difference rises at this rate, so lateness that lasts is absorbed into it no
    /// faster (0.2 ms per second at the default, [`CLOCK_DRIFT`]).
    pub clock_drift: f64,
    /// Smallest (host − device) clock difference, s, allowing for drift; None before a report.
    clock_floor: Option<f64>,
    last_device_time: f64,
}

use crate::transport::CLOCK_DRIFT;

impl TimingStats {
    pub fn new(nominal_period: f64) -> Self {
        Self {
            nominal_period,
            period: Histogram::new(20_000),
            compute: Histogram::new(5_000),
            lateness: Histogram::new(20_000),
            ticks: 0,
            late: 0,
            late_wakeups: 0,
            missed: 0,
            overruns: 0,
            garbled: 0,
            watchdog_faults: 0,
            device_fault_ticks: 0,
            non_finite_forces: 0,
            clock_jumps_back: 0,
            clock_drift: CLOCK_DRIFT,
            clock_floor: None,
            last_device_time: 0.0,
        }
    }

    /// Compare the two clocks afresh from the next report (after a silence or a device reset,
    /// when their offset may have changed).
    pub fn restart_lateness(&mut self) {
        self.clock_floor = None;
    }

    /// Record a report received at host time `received` (s) with device time `device` (s). The
    /// difference of the two clocks is an unknown constant plus the report's lateness; the
    /// constant is the smallest difference seen, let rise by `clock_drift` so a slow device
    /// clock is not mistaken for growing lateness. Allocation-free.
    pub fn record_lateness(&mut self, received: f64, device: f64) {
        let difference = received - device;
        let floor = match self.clock_floor {
            Some(floor) => {
                let elapsed = (device - self.last_device_time).max(0.0);
                (floor + self.clock_drift * elapsed).min(difference)
            }
            None => difference,
        };
        self.clock_floor = Some(floor);
        self.last_device_time = device;
        let lateness = difference - floor;
        self.lateness.record_ns((lateness * 1e9) as u64);
        if lateness > self.nominal_period {
            self.late_wakeups += 1;
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
        let tail = |h: &Histogram| {
            let [p50, p99, p999] = [0.5, 0.99, 0.999].map(|p| q(h, p));
            format!("p50 {p50}  p99 {p99}  p99.9 {p999}  max {:.0}", h.max_us())
        };
        writeln!(f, "  period µs     {}", tail(&self.period))?;
        writeln!(
            f,
            "  lateness µs   {}  (more than a period late: {})",
            tail(&self.lateness),
            self.late_wakeups
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
            "  late {}  missed {}  overruns {}  garbled {}  watchdog faults {}  device-fault ticks {}  non-finite forces {}  clock jumps back {}",
            self.late,
            self.missed,
            self.overruns,
            self.garbled,
            self.watchdog_faults,
            self.device_fault_ticks,
            self.non_finite_forces,
            self.clock_jumps_back
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

    #[test]
    fn no_quantile_exceeds_the_maximum() {
        // A virtual-time loop: every period exactly 1 ms, the lower edge of the 1000 µs bin.
        let mut h = Histogram::new(20_000);
        for _ in 0..1000 {
            h.record_ns(1_000_000);
        }
        assert_eq!(h.max_us(), 1000.0);
        for p in [0.5, 0.99, 0.999, 1.0] {
            assert_eq!(h.quantile_us(p), Some(1000.0), "p = {p}");
        }
        // Within a bin, a quantile is its upper edge unless that is above the maximum.
        h.record_ns(1_000_400);
        assert_eq!(h.quantile_us(1.0), Some(1000.4));
        h.record_ns(2_500_000);
        assert_eq!(h.quantile_us(0.999), Some(1001.0));
        assert_eq!(h.quantile_us(1.0), Some(2500.0));
    }

    #[test]
    fn lateness_is_measured_against_the_device_timestamps() {
        let mut s = TimingStats::new(1e-3);
        // Host clock 5 s ahead of the device's; every report 20 µs late, then one 1.5 ms late.
        for k in 0..1000 {
            let due = k as f64 * 1e-3;
            s.record_lateness(5.0 + due + 20e-6, due);
        }
        s.record_lateness(5.0 + 1.0 + 1.5e-3, 1.0);
        // A constant delay is indistinguishable from the clock offset: lateness counts from it.
        assert_eq!(s.lateness.quantile_us(0.5), Some(1.0));
        assert!((s.lateness.max_us() - 1480.0).abs() < 2.0);
        assert_eq!(s.late_wakeups, 1);
    }

    #[test]
    fn a_restart_compares_the_clocks_afresh() {
        let mut s = TimingStats::new(1e-3);
        s.record_lateness(0.0, 0.0);
        // The device reset during a 2 s silence: its clock starts again near zero.
        s.restart_lateness();
        for k in 0..100 {
            s.record_lateness(2.0 + k as f64 * 1e-3, k as f64 * 1e-3);
        }
        assert_eq!(s.late_wakeups, 0);
        assert!(s.lateness.max_us() < 1.0);
    }

    #[test]
    fn a_slow_device_clock_is_not_mistaken_for_lateness() {
        let mut s = TimingStats::new(1e-3);
        // The device clock runs 100 ppm slow for 60 s: the difference grows by 6 ms.
        for k in 0..60_000 {
            let host = k as f64 * 1e-3;
            s.record_lateness(host, host * (1.0 - 1e-4));
        }
        assert!(s.lateness.max_us() < 2.0, "{}", s.lateness.max_us());
        assert_eq!(s.late_wakeups, 0);
    }
}
