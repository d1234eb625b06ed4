//! The baseline for hgcd's loop timing: a bare 1 kHz loop that does nothing but sleep to absolute
//! 1 ms deadlines on CLOCK_MONOTONIC, set up for real time exactly as hgcd's servo thread is
//! (SCHED_FIFO where permitted, memory locked, timer slack 1 ns), and measures how late each
//! wake-up is against its deadline: what this machine and kernel allow at best.
//!
//! `cargo run --release --example bare_loop -- 30` (seconds; run as root for SCHED_FIFO), next to
//! `hgcd run --device sim:point-mass --duration 30`, whose "lateness" line measures the same thing
//! for the real loop (see docs/performance.md).

use std::time::{Duration, Instant};

use hgcd::config::ServoConfig;
use hgcd::servo::rt;
use hgcd::servo::stats::Histogram;
use hgcd::sys::sleep_until;

fn main() -> std::process::ExitCode {
    let seconds: f64 = match std::env::args().nth(1).map(|s| s.parse::<f64>()) {
        None => 10.0,
        Some(Ok(s)) if s.is_finite() && s > 0.0 => s,
        Some(_) => {
            eprintln!(
                "bare_loop: the one argument is how long to run, a positive number of seconds"
            );
            return std::process::ExitCode::FAILURE;
        }
    };
    let setup = rt::prepare_current_thread(&ServoConfig::default());
    for w in &setup.warnings {
        eprintln!("warning: {w}");
    }
    let period = Duration::from_millis(1);
    let periods = (seconds * 1000.0) as u64;
    let mut lateness = Histogram::new(20_000);
    let mut late = 0u64;
    let mut fastest = Duration::MAX;
    let start = Instant::now();
    for k in 1..=periods {
        let deadline = start + period * k as u32;
        sleep_until(deadline);
        let woke = Instant::now().saturating_duration_since(deadline);
        lateness.record_ns(woke.as_nanos() as u64);
        fastest = fastest.min(woke);
        if woke > period {
            late += 1;
        }
    }
    let q = |p| lateness.quantile_us(p).unwrap_or(0.0);
    println!(
        "bare loop: {periods} periods at 1000 Hz, {}",
        setup
            .fifo_priority
            .map_or("normal scheduling".into(), |p| format!("SCHED_FIFO {p}"))
    );
    println!(
        "  lateness µs   p50 {:.0}  p99 {:.0}  p99.9 {:.0}  max {:.0}  (more than a period late: {late})",
        q(0.5),
        q(0.99),
        q(0.999),
        lateness.max_us()
    );
    // hgcd cannot see the wake-up latency every report shares (it is indistinguishable from the
    // offset between the device's clock and the host's), so it counts lateness from the fastest
    // report: the same here, for a like-for-like comparison.
    let min = fastest.as_secs_f64() * 1e6;
    println!(
        "  beyond the fastest wake-up ({min:.0} µs): p50 {:.0}  p99 {:.0}  p99.9 {:.0}  max {:.0}",
        q(0.5) - min,
        q(0.99) - min,
        q(0.999) - min,
        lateness.max_us() - min
    );
    std::process::ExitCode::SUCCESS
}
