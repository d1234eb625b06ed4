//! FOAW cost per sample on one axis: a noisy, quantised 1 kHz sine
//! (20 mm, 1 Hz; 3 µm uniform noise, 2 µm quantisation, d = 4 µm).
//!
//! One iteration = one `update`, so criterion's time per iteration is the
//! time per sample.

use criterion::{black_box, criterion_group, criterion_main, Criterion, Throughput};
use hgcd::estimate::{FoawAxis, FoawVariant};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::Uniform;
use std::f64::consts::TAU;

const T: f64 = 1e-3;
const NOISE: f64 = 3e-6;
const Q: f64 = 2e-6;

/// Four whole periods, so cycling through the record has no seam.
fn signal() -> Vec<f64> {
    let mut rng = ChaCha8Rng::seed_from_u64(42);
    let noise = Uniform::new_inclusive(-NOISE, NOISE);
    (0..4000)
        .map(|k| {
            let x = 0.02 * (TAU * k as f64 * T).sin() + rng.sample(noise);
            (x / Q).round() * Q
        })
        .collect()
}

fn bench_foaw(c: &mut Criterion) {
    let sig = signal();
    let mut group = c.benchmark_group("foaw");
    group.throughput(Throughput::Elements(1));
    for (name, variant) in [
        ("end-fit", FoawVariant::EndFit),
        ("best-fit", FoawVariant::BestFit),
    ] {
        for window in [16, 32] {
            let mut f = FoawAxis::new(variant, NOISE + Q / 2.0, window, T).unwrap();
            // Warm up the history so every timed sample sees a full window.
            sig.iter().for_each(|&x| {
                f.update(x);
            });
            let mut i = 0;
            group.bench_function(format!("{name}/{window}"), |b| {
                b.iter(|| {
                    let x = sig[i];
                    i = if i + 1 == sig.len() { 0 } else { i + 1 };
                    f.update(black_box(x))
                })
            });
        }
    }
    group.finish();
}

criterion_group!(benches, bench_foaw);
criterion_main!(benches);
