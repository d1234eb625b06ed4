//! FOAW cost per sample on one axis, hgcd against the public C reference on identical inputs in
//! the same run: a noisy, quantised 1 kHz sine (20 mm, 1 Hz; ±3 µm uniform noise, 2 µm quantum,
//! d = 4 µm), 4000 samples.
//!
//! `cargo bench --bench foaw`. The reference is Stephen Sinclair's `cvelocity.c` (radarsat1/FOAW,
//! BSD-licensed), which is not part of this repository: the benchmark compiles it with
//! `cc -O2 -fPIC -shared` from `$FOAW_REFERENCE`, by default `../shared/reference/foaw/cvelocity.c`
//! beside the repository, into a library under cargo's target directory, and calls its
//! `foaw_end_fit` / `foaw_best_fit` on the whole record. If the file is missing or does not
//! compile, the benchmark says why and times hgcd alone.
//!
//! Both sides start each pass from a history pre-filled with the first sample (the reference's
//! buffer of n + 1 samples is a window of n periods). Each round times one pass per side and
//! configuration, in alternating order; the figures are medians over the rounds, with the
//! interquartile range of the per-round ratio, because on a shared machine other jobs slow some
//! rounds. Without `--bench` (as under `cargo test --benches`) it runs one round as a smoke test.

use std::env;
use std::ffi::{c_int, c_void, CStr, CString};
use std::hint::black_box;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use hgcd::estimate::{FoawAxis, FoawVariant};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::Uniform;
use std::f64::consts::TAU;

const T: f64 = 1e-3;
const AMPLITUDE: f64 = 0.02;
const NOISE: f64 = 3e-6;
const Q: f64 = 2e-6;
const D: f64 = NOISE + Q / 2.0;
const WINDOWS: [usize; 2] = [16, 32];
const VARIANTS: [(&str, FoawVariant); 2] = [
    ("end-fit", FoawVariant::EndFit),
    ("best-fit", FoawVariant::BestFit),
];
/// Samples left out of the accuracy figures while the pre-filled history drains.
const SETTLE: usize = 100;

/// Four whole periods, so the record has no seam when passes repeat.
fn signal() -> Vec<f64> {
    let mut rng = ChaCha8Rng::seed_from_u64(42);
    let noise = Uniform::new_inclusive(-NOISE, NOISE);
    (0..4000)
        .map(|k| {
            let x = AMPLITUDE * (TAU * k as f64 * T).sin() + rng.sample(noise);
            (x / Q).round() * Q
        })
        .collect()
}

fn true_velocity(k: usize) -> f64 {
    AMPLITUDE * TAU * (TAU * k as f64 * T).cos()
}

/// `foaw_end_fit` / `foaw_best_fit` of `cvelocity.c`:
/// `(sample rate, buffer size, noise bound, input, output, length)`.
type RefFn = unsafe extern "C" fn(f64, c_int, f64, *mut f64, *mut f64, c_int);

struct Reference {
    end_fit: RefFn,
    best_fit: RefFn,
}

impl Reference {
    /// Compiles the reference and loads it, or says why not.
    fn load() -> Result<Self, String> {
        let source = env::var_os("FOAW_REFERENCE").map_or_else(
            || Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/reference/foaw/cvelocity.c"),
            PathBuf::from,
        );
        if !source.is_file() {
            return Err(format!(
                "C reference not found at {} (set FOAW_REFERENCE to radarsat1/FOAW's \
                 cvelocity.c to compare)",
                source.display()
            ));
        }
        let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("foaw-reference");
        std::fs::create_dir_all(&dir)
            .map_err(|e| format!("cannot create {}: {e}", dir.display()))?;
        let lib = dir.join("libcvelocity.so");
        let cc = env::var("CC").unwrap_or_else(|_| "cc".into());
        let out = Command::new(&cc)
            .args(["-O2", "-fPIC", "-shared", "-o"])
            .arg(&lib)
            .arg(&source)
            .arg("-lm")
            .output()
            .map_err(|e| format!("cannot run {cc} to compile the C reference: {e}"))?;
        if !out.status.success() {
            let stderr = String::from_utf8_lossy(&out.stderr);
            return Err(format!(
                "{cc} failed on {} ({})",
                source.display(),
                stderr
                    .lines()
                    .find(|l| l.contains("error"))
                    .unwrap_or("no message")
            ));
        }
        let path = CString::new(lib.as_os_str().as_encoded_bytes())
            .map_err(|_| format!("library path {} contains NUL", lib.display()))?;
        // SAFETY: dlopen with a valid C string; the library has no initialisers of its own.
        let handle = unsafe { libc::dlopen(path.as_ptr(), libc::RTLD_NOW | libc::RTLD_LOCAL) };
        if handle.is_null() {
            return Err(format!("cannot load {}: {}", lib.display(), dl_error()));
        }
        let symbol = |name: &CStr| -> Result<RefFn, String> {
            // SAFETY: valid handle and C string.
            let sym = unsafe { libc::dlsym(handle, name.as_ptr()) };
            if sym.is_null() {
                return Err(format!("{} lacks {name:?}: {}", lib.display(), dl_error()));
            }
            // SAFETY: both symbols are defined in cvelocity.c with exactly the RefFn signature
            // (`void f(double, int, double, double *, double *, int)`). The library stays
            // loaded for the life of the process.
            Ok(unsafe { std::mem::transmute::<*mut c_void, RefFn>(sym) })
        };
        Ok(Self {
            end_fit: symbol(c"foaw_end_fit")?,
            best_fit: symbol(c"foaw_best_fit")?,
        })
    }

    fn run(&self, variant: FoawVariant, window: usize, x: &[f64], out: &mut [f64]) {
        let f = match variant {
            FoawVariant::EndFit => self.end_fit,
            FoawVariant::BestFit => self.best_fit,
        };
        assert_eq!(x.len(), out.len());
        let len = c_int::try_from(x.len()).expect("record fits a C int");
        // SAFETY: the reference only reads `len` inputs and writes `len` outputs; its buffer
        // of window + 1 samples lives on its own stack. It never writes through `input`.
        unsafe {
            f(
                1.0 / T,
                (window + 1) as c_int,
                D,
                x.as_ptr().cast_mut(),
                out.as_mut_ptr(),
                len,
            )
        };
    }
}

fn dl_error() -> String {
    // SAFETY: dlerror returns NULL or a valid C string owned by libc.
    let e = unsafe { libc::dlerror() };
    if e.is_null() {
        "unknown error".into()
    } else {
        // SAFETY: non-null pointer from dlerror.
        unsafe { CStr::from_ptr(e) }.to_string_lossy().into_owned()
    }
}

fn run_hgcd(f: &mut FoawAxis, x: &[f64], out: &mut [f64]) {
    f.reset();
    for (o, &xi) in out.iter_mut().zip(x) {
        *o = f.update(black_box(xi));
    }
}

/// Nanoseconds per sample of one pass of `run` over `len` samples.
fn ns_per_sample(len: usize, run: impl FnOnce()) -> f64 {
    let start = Instant::now();
    run();
    start.elapsed().as_nanos() as f64 / len as f64
}

/// First quartile, median and third quartile.
fn quartiles(v: &mut [f64]) -> [f64; 3] {
    v.sort_by(f64::total_cmp);
    [1, 2, 3].map(|q| v[(q * (v.len() - 1)) / 4])
}

fn rms_error_mm_s(v: &[f64]) -> f64 {
    let sq: f64 = (SETTLE..v.len())
        .map(|k| (v[k] - true_velocity(k)).powi(2))
        .sum();
    1e3 * (sq / (v.len() - SETTLE) as f64).sqrt()
}

/// Per-round timings of one configuration.
#[derive(Default)]
struct Timings {
    hgcd: Vec<f64>,
    reference: Vec<f64>,
    ratio: Vec<f64>,
}

fn main() {
    let rounds = if env::args().any(|a| a == "--bench") {
        201
    } else {
        1
    };
    let x = signal();
    let (mut out_h, mut out_c) = (vec![0.0; x.len()], vec![0.0; x.len()]);
    let reference = Reference::load()
        .inspect_err(|why| println!("foaw: {why}; timing hgcd alone"))
        .ok();
    let configs: Vec<(&str, FoawVariant, usize)> = VARIANTS
        .iter()
        .flat_map(|&(name, v)| WINDOWS.map(|w| (name, v, w)))
        .collect();
    let mut axes: Vec<FoawAxis> = configs
        .iter()
        .map(|&(_, v, w)| FoawAxis::new(v, D, w, T).expect("valid FOAW parameters"))
        .collect();
    let mut timings: Vec<Timings> = configs.iter().map(|_| Timings::default()).collect();

    // Round 0 warms caches and branch predictors and is not counted.
    for round in 0..=rounds {
        for ((&(_, v, w), f), t) in configs.iter().zip(&mut axes).zip(&mut timings) {
            let mut h = |out: &mut [f64]| ns_per_sample(x.len(), || run_hgcd(f, &x, out));
            let (th, tc) = match &reference {
                None => (h(&mut out_h), f64::NAN),
                Some(r) => {
                    let c = |out: &mut [f64]| ns_per_sample(x.len(), || r.run(v, w, &x, out));
                    if round % 2 == 0 {
                        let th = h(&mut out_h);
                        (th, c(&mut out_c))
                    } else {
                        let tc = c(&mut out_c);
                        (h(&mut out_h), tc)
                    }
                }
            };
            black_box((&out_h, &out_c));
            if round > 0 {
                t.hgcd.push(th);
                t.reference.push(tc);
                t.ratio.push(th / tc);
            }
        }
    }

    println!(
        "FOAW, one axis, {} samples of a 20 mm 1 Hz sine at 1 kHz, ±3 µm noise, 2 µm quantum, \
         d = 4 µm: {}",
        x.len(),
        if rounds == 1 {
            "one round (smoke run; pass --bench)".to_string()
        } else {
            format!("medians of {rounds} rounds")
        }
    );
    println!(
        "{:<9} {:>6} {:>11} {:>9} {:>7} {:>13}   velocity RMS error (mm/s)",
        "variant", "window", "hgcd ns", "C ns", "hgcd/C", "ratio IQR"
    );
    for ((&(name, v, w), f), t) in configs.iter().zip(&mut axes).zip(&mut timings) {
        run_hgcd(f, &x, &mut out_h);
        let hgcd = quartiles(&mut t.hgcd)[1];
        let rms = rms_error_mm_s(&out_h);
        match &reference {
            None => println!("{name:<9} {w:>6} {hgcd:>11.1}   (no reference)   hgcd {rms:.3}"),
            Some(r) => {
                r.run(v, w, &x, &mut out_c);
                let [lo, ratio, hi] = quartiles(&mut t.ratio);
                println!(
                    "{name:<9} {w:>6} {hgcd:>11.1} {:>9.1} {ratio:>7.2} {lo:>6.2}–{hi:<6.2}   \
                     hgcd {rms:.3}, C {:.3}",
                    quartiles(&mut t.reference)[1],
                    rms_error_mm_s(&out_c)
                );
            }
        }
    }
}
