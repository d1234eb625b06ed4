//! Fuzzing the profile parser with proptest: arbitrary text, TOML-like token soup, mutated
//! built-in profiles and profiles of a valid shape with any numbers never panic; each either
//! loads as a profile that keeps every rule of `docs/devices.md` or is refused with a
//! `ProfileError` of one line.
//!
//! The default case count keeps `cargo test` fast; for a long run:
//! `PROPTEST_CASES=100000 cargo test --release --lib profile::fuzz`.

use nalgebra::Vector3;
use proptest::prelude::*;

use super::woodenhaptics::{CurrentReport, EncoderReport, REPORT_LEN};
use super::{Profile, ProfileError, BUILT_IN, NAME_LEN, RANGES};
use crate::protocol::fuzz::{self, mostly, text_properties, toml_token};
use crate::protocol::OUTPUT_REPORT_LEN;

/// Pieces of TOML and of profiles, the kind of thing a mutation should insert.
fn token() -> BoxedStrategy<String> {
    prop_oneof![
        toml_token(),
        Just("[kinematics]\n".to_string()),
        Just("[bodies]\n".to_string()),
        Just("[arm]\n".to_string()),
        Just("protocol = \"woodenhaptics\"\n".to_string()),
        Just("protocol = \"cartesian-v1\"\n".to_string()),
        Just("kind = \"serial\"\n".to_string()),
        Just("kind = \"delta\"\n".to_string()),
        Just("max_force_n = 5\n".to_string()),
        Just("\"ffff:ffff\"".to_string()),
        Just("\"-z\"".to_string()),
        Just("legs_deg = [0, 0, 0]\n".to_string()),
        Just("home_counts = [32767, -32768, 0]\n".to_string()),
        Just("axes = [\"x\", \"x\", \"z\"]\n".to_string()),
    ]
    .boxed()
}

/// A number as TOML writes it (`nan`, `inf`: Rust's `NaN` is no TOML).
fn toml(v: f64) -> String {
    format!("{v:?}").replace("NaN", "nan")
}

fn list(values: &[f64]) -> String {
    let items: Vec<String> = values.iter().map(|v| toml(*v)).collect();
    format!("[{}]", items.join(", "))
}

/// Whether every value of `key` lies in its range.
fn in_range(key: &str, values: &[f64]) -> bool {
    let &(_, min, max, _) = RANGES.iter().find(|r| r.0 == key).expect("a ranged key");
    values.iter().all(|v| (min..=max).contains(v))
}

/// What every outcome of the parser must satisfy.
fn loads_soundly_or_is_refused_in_one_line(text: &str) -> Result<(), TestCaseError> {
    let profile = match Profile::parse(text, "fuzz.toml") {
        Err(e) => {
            let message = e.to_string();
            prop_assert!(!message.contains('\n'), "{message:?}");
            prop_assert!(
                matches!(
                    e,
                    ProfileError::Invalid { .. } | ProfileError::OutOfRange { .. }
                ),
                "{message}"
            );
            return Ok(());
        }
        Ok(profile) => profile,
    };
    let name_ok = |c: char| c.is_ascii_alphanumeric() || c == '-' || c == '_';
    prop_assert!((1..=NAME_LEN).contains(&profile.name.len()));
    prop_assert!(profile.name.chars().all(name_ok), "{}", profile.name);
    prop_assert_eq!(profile.max_force.is_some(), profile.arm().is_some());
    if let Some(f) = profile.max_force {
        prop_assert!(in_range("max_force_n", &[f]));
    }
    if let Some(b) = &profile.bodies {
        prop_assert!(profile.arm().is_some());
        prop_assert!(in_range("bodies.masses_kg", &b.masses_kg));
        prop_assert!(in_range("bodies.centres_of_mass_m", &b.centres_of_mass_m));
    }
    if let Some(arm) = profile.arm() {
        prop_assert!(arm.joints_at(&Vector3::zeros()).is_some());
        let info = profile
            .device_info(1000.0)
            .expect("a joint-space device's info");
        prop_assert!(info.max_force.is_finite() && info.workspace_half_extents.x > 0.0);
        // Any counts read as a finite position; any force as currents within full scale.
        let mut codec = profile.codec();
        let full_scale = arm.max_current * 1e3;
        for counts in [arm.home_counts, [0; 3], [i16::MAX, i16::MIN, i16::MAX]] {
            let mut bytes = [0; REPORT_LEN];
            let [a, b, c] = counts;
            EncoderReport {
                counts: [a, b, c, 0, 0, 0],
                info: 0,
            }
            .encode(&mut bytes);
            let sample = codec.decode(&bytes).expect("a report of the right length");
            prop_assert!(sample.position.iter().all(|c| c.is_finite()));
            let mut out = [0; OUTPUT_REPORT_LEN];
            let force = Vector3::new(1.0, -2.0, 3.0);
            let n = codec.encode(0, &force, true, &mut out);
            let sent = CurrentReport::decode(&out[..n]).expect("a report of the right length");
            prop_assert!(sent
                .currents_ma
                .iter()
                .all(|&ma| f64::from(ma).abs() <= full_scale + 0.5));
        }
    }
    // The arm the gravity model knows holds the handle at the device's origin, finitely.
    if let Some(arm) = profile.gravity_arm() {
        let at_origin = arm.force_regressor(&Vector3::zeros(), &arm.up(), 9.81);
        prop_assert!(
            at_origin.is_some_and(|g| g.iter().all(|c| c.is_finite())),
            "{arm:?}"
        );
    }
    Ok(())
}

/// A WoodenHaptics-protocol profile with these numbers.
#[allow(clippy::too_many_arguments)]
fn joint_space(
    lengths: [f64; 3],
    capstans: [f64; 3],
    drums: [f64; 3],
    counts: [f64; 3],
    torque: f64,
    current: f64,
    origin: [f64; 3],
    radius: f64,
    home: [i16; 3],
    bodies: [f64; 4],
) -> String {
    format!(
        "name = \"w\"\ndescription = \"\"\nprotocol = \"woodenhaptics\"\nmax_force_n = 5.0\n\
         [kinematics]\nlengths_m = {}\ncapstan_diameters_m = {}\ndrum_diameters_m = {}\n\
         motor_and_body_aligned = [false, true, false]\ncounts_per_rev = {}\n\
         torque_constants_nm_per_a = {}\nmax_current_a = {}\nworkspace_origin_m = {}\n\
         workspace_radius_m = {}\nhome_counts = {home:?}\n\
         [bodies]\nmasses_kg = {}\ncentres_of_mass_m = {}\n",
        list(&lengths),
        list(&capstans),
        list(&drums),
        list(&counts),
        list(&[torque; 3]),
        toml(current),
        list(&origin),
        toml(radius),
        list(&bodies[..2]),
        list(&bodies[2..]),
    )
}

/// A Cartesian profile with an `[arm]` table of these numbers: a serial arm (shoulder, upper,
/// fore) or a delta (arm, rod, base and platform radii, pivot height, legs).
fn with_arm(
    delta: bool,
    lengths: [f64; 5],
    legs: [f64; 3],
    axes: [&str; 3],
    origin: [f64; 3],
) -> String {
    let [a, b, c, d, e] = lengths.map(toml);
    let geometry = if delta {
        format!(
            "kind = \"delta\"\narm_m = {a}\nrod_m = {b}\nbase_radius_m = {c}\n\
             platform_radius_m = {d}\npivot_height_m = {e}\nlegs_deg = {}\n",
            list(&legs)
        )
    } else {
        format!(
            "kind = \"serial\"\nshoulder_m = {}\nupper_m = {d}\nfore_m = {e}\n",
            list(&lengths[..3])
        )
    };
    format!(
        "name = \"a\"\ndescription = \"\"\nprotocol = \"cartesian-v1\"\n[arm]\n{geometry}\
         axes = {axes:?}\norigin_m = {}\n",
        list(&origin)
    )
}

fn triple(range: std::ops::Range<f64>) -> impl Strategy<Value = [f64; 3]> {
    [mostly(range.clone()), mostly(range.clone()), mostly(range)]
}

/// Mostly a signed permutation of x, y, z; sometimes anything.
fn axes() -> impl Strategy<Value = [&'static str; 3]> {
    let any_axis = || prop::sample::select(vec!["x", "y", "z", "-x", "-y", "-z", "+z", "w", ""]);
    prop_oneof![
        3 => Just(["x", "y", "z"]),
        1 => Just(["-y", "+x", "z"]),
        2 => [any_axis(), any_axis(), any_axis()],
    ]
}

text_properties!(
    fuzz::cases(512),
    loads_soundly_or_is_refused_in_one_line,
    token,
    prop::sample::select(BUILT_IN).prop_map(|(_, text)| text.to_string())
);

proptest! {
    #![proptest_config(fuzz::cases(512))]

    #[test]
    fn joint_space_profiles_of_any_numbers_never_panic(
        lengths in triple(0.0..0.3), capstans in triple(0.001..0.05),
        drums in triple(0.005..0.3), counts in triple(4.0..1e5),
        torque in mostly(0.001..0.1), current in mostly(0.01..30.0),
        origin in [mostly(0.1..0.3), mostly(-0.05..0.05), mostly(0.0..0.15)],
        radius in mostly(0.005..0.2), home in any::<[i16; 3]>(),
        bodies in [mostly(0.0..1.0), mostly(0.0..1.0), mostly(-0.3..0.3), mostly(-0.3..0.3)],
    ) {
        let text = joint_space(
            lengths, capstans, drums, counts.map(f64::round), torque, current, origin, radius,
            home, bodies,
        );
        loads_soundly_or_is_refused_in_one_line(&text)?;
    }

    #[test]
    fn arm_tables_of_any_numbers_never_panic(
        delta in any::<bool>(),
        lengths in [mostly(-0.3..0.3), mostly(-0.3..0.3), mostly(0.0..0.3), mostly(0.0..0.3), mostly(0.0..0.3)],
        legs in triple(-360.0..360.0), axes in axes(), origin in triple(-0.1..0.1),
    ) {
        loads_soundly_or_is_refused_in_one_line(&with_arm(delta, lengths, legs, axes, origin))?;
    }
}

#[test]
fn the_valid_shapes_the_numbers_go_into_load() {
    let wooden = joint_space(
        [0.08, 0.205, 0.245],
        [0.01; 3],
        [0.16, 0.12, 0.12],
        [2000.0; 3],
        0.0259,
        6.0,
        [0.22, 0.0, 0.08],
        0.1,
        [0, 0, 6000],
        [0.17, 0.11, 0.051, 0.091],
    );
    assert!(Profile::parse(&wooden, "w").unwrap().arm().is_some());
    let serial = [-0.215, 0.0, 0.17, 0.215, 0.17];
    let delta = [0.06, 0.1025, 0.037, 0.014, 0.09];
    for (is_delta, lengths) in [(false, serial), (true, delta)] {
        let text = with_arm(
            is_delta,
            lengths,
            [180.0, -60.0, 60.0],
            ["x", "y", "z"],
            [0.0; 3],
        );
        assert!(
            Profile::parse(&text, "a").unwrap().gravity_arm().is_some(),
            "{text}"
        );
    }
}
