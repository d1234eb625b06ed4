//! One millisecond of a simulated linkage: the ten 0.1 ms substeps (`sim.substep_hz`) the
//! simulated firmware integrates per report, for `sim:phantom` and `sim:delta` without and with
//! 0.04 N of friction at the handle, held against gravity and pushed by a slow sine of about
//! 0.44 N so the joints stick and slide as they do in a calibration's strokes.
//!
//! `cargo bench --bench sim_step`. The plants are what the test suite spends most of its time
//! in (every calibration and validation runs in virtual time), so this is the figure that moves
//! the suite's length; docs/performance.md has the numbers.

use std::hint::black_box;
use std::time::Duration;

use criterion::{criterion_group, criterion_main, Criterion};
use nalgebra::Vector3;

use hgcd::config::SimConfig;
use hgcd::sim::{delta, phantom, Plant};

const SUBSTEPS: usize = 10;
const DT: f64 = 1e-4;

/// Runs `plant` for one simulated millisecond per iteration, the push's phase advancing with
/// device time.
fn one_millisecond(c: &mut Criterion, name: &str, mut plant: Box<dyn Plant>) {
    let hold = plant.holding_force();
    let mut t = 0.0_f64;
    c.bench_function(name, |b| {
        b.iter(|| {
            let push = Vector3::new(0.3, -0.2, 0.25) * (std::f64::consts::TAU * 0.5 * t).sin();
            for _ in 0..SUBSTEPS {
                plant.step(black_box(&(hold + push)), DT);
            }
            t = (t + 1e-3) % 2.0;
            black_box(plant.position())
        })
    });
}

fn bench_plants(c: &mut Criterion) {
    for (friction, at_handle) in [("frictionless_handle", 0.0), ("handle_friction", 0.04)] {
        let sim = SimConfig {
            coulomb_friction_n: at_handle,
            ..SimConfig::default()
        };
        one_millisecond(
            c,
            &format!("sim_step/phantom_1ms/{friction}"),
            Box::new(phantom::from_config(&sim).unwrap()),
        );
        one_millisecond(
            c,
            &format!("sim_step/delta_1ms/{friction}"),
            Box::new(delta::from_config(&sim).unwrap()),
        );
    }
}

criterion_group! {
    name = benches;
    config = Criterion::default().measurement_time(Duration::from_secs(5));
    targets = bench_plants
}
criterion_main!(benches);
