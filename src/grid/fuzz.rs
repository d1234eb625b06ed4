//! Fuzzing the grid loader with proptest: arbitrary text, TOML-like token soup and mutated valid
//! files never panic; each either loads as a grid that keeps every rule of the format and
//! survives a save/load round trip, or is refused with a `GridError` of one line.
//!
//! The default case count keeps `cargo test` fast; for a long run:
//! `PROPTEST_CASES=200000 cargo test --release --lib grid::fuzz`.

use std::path::Path;

use nalgebra::Vector3;
use proptest::prelude::*;

use super::file::tests::calibrated;
use super::file::GridFile;
use super::lattice::tests::sample;
use super::GridError;
use crate::protocol::fuzz::{self, near, text_properties, toml_token};

/// A valid file with every table the format knows and an unknown one.
fn valid_text() -> String {
    let mut file = calibrated();
    if let Some(c) = &mut file.calibration {
        c.n_init = Some(30);
        c.left_out_vertices = Some(vec![[-2, -2, -2], [2, 2, 2]]);
    }
    let mut text = file.to_toml_string();
    text.push_str("\n[future]\nkey = \"value\"\nwhen = 1979-05-27\n");
    text
}

/// Pieces of TOML and of grid files, the kind of thing a mutation should insert.
fn token() -> BoxedStrategy<String> {
    prop_oneof![
        toml_token(),
        Just("\"hgcd-grid/1\"".to_string()),
        Just("[device]\n".to_string()),
        Just("[calibration]\n".to_string()),
        Just("[vertices]\n".to_string()),
        Just("[[vertices]]\n".to_string()),
        Just("dims = [1000, 1000, 1000]\n".to_string()),
        Just("masses = []\n".to_string()),
        Just("g = 9.81\n".to_string()),
        Just("force_vectors = [[1, 2]]\n".to_string()),
    ]
    .boxed()
}

/// What every outcome of the loader must satisfy.
fn loads_soundly_or_is_refused_in_one_line(text: &str) -> Result<(), TestCaseError> {
    let path = Path::new("fuzz.toml");
    match GridFile::from_toml_str(text, path) {
        Err(e) => {
            let message = e.to_string();
            prop_assert!(!message.contains('\n'), "{message:?}");
            prop_assert!(
                matches!(e, GridError::Syntax { .. } | GridError::Invalid { .. }),
                "{message}"
            );
        }
        Ok(file) => {
            prop_assert_eq!(file.check(), Ok(()));
            let grid = &file.grid;
            let far = grid.far_corner();
            for x in [
                grid.origin,
                far,
                (grid.origin + far) / 2.0,
                Vector3::new(1e3, -1e3, 0.5),
                Vector3::repeat(f64::MAX),
            ] {
                prop_assert!(grid.mass_at(&x).is_finite());
                prop_assert!(grid.gravity_force(&x).iter().all(|c| c.is_finite()));
            }
            // What was loaded saves and loads back the same (the direction, already normalised,
            // may move by an ulp when normalised again).
            let text = file.to_toml_string();
            let mut again = GridFile::from_toml_str(&text, path)
                .map_err(|e| TestCaseError::fail(format!("{e}\n{text}")))?;
            let drift = (again.grid.gravity_direction - grid.gravity_direction).norm();
            prop_assert!(drift < 1e-15);
            again.grid.gravity_direction = grid.gravity_direction;
            prop_assert_eq!(again.to_toml_string(), text);
        }
    }
    Ok(())
}

text_properties!(
    fuzz::cases(256),
    loads_soundly_or_is_refused_in_one_line,
    token,
    Just(valid_text())
);

proptest! {
    #[test]
    fn arbitrary_values_in_a_valid_shape_never_panic(
        g in near(8.0..12.0), dx in near(-1e-3..1e-3), spacing in near(1e-3..0.5),
        ox in near(-10.0..10.0), nx in -2i64..5,
        masses in proptest::collection::vec(near(-100.0..100.0), 0..10),
        forces in proptest::collection::vec([near(-5.0..5.0), near(-5.0..5.0), near(0.0..20.0)], 0..10),
    ) {
        let text = format!(
            "format = \"hgcd-grid/1\"\ng = {g:?}\ngravity_direction = [{dx:?}, 0.0, 1.0]\n\
             origin = [{ox:?}, 0.0, 0.0]\nspacing = {spacing:?}\ndims = [{nx}, 1, 1]\n\
             masses = {masses:?}\n[vertices]\nforce_vectors = {forces:?}\n"
        )
        .replace("NaN", "nan");
        loads_soundly_or_is_refused_in_one_line(&text)?;
    }

    #[test]
    fn arbitrary_bytes_in_a_file_never_panic(
        bytes in proptest::collection::vec(any::<u8>(), 0..300), valid_prefix in any::<bool>(),
    ) {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("dev.toml");
        let mut content = if valid_prefix { valid_text().into_bytes() } else { Vec::new() };
        content.extend_from_slice(&bytes);
        std::fs::write(&path, &content).unwrap();
        match GridFile::load(&path) {
            Ok(file) => prop_assert_eq!(file.check(), Ok(())),
            Err(e) => prop_assert!(!e.to_string().contains('\n')),
        }
    }
}

#[test]
fn the_valid_file_the_mutations_start_from_loads() {
    let file = GridFile::from_toml_str(&valid_text(), Path::new("valid.toml")).unwrap();
    assert_eq!(file.grid, sample());
}
