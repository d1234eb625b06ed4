//! Fuzzing the model-file parser with proptest: arbitrary text, TOML-like token soup, mutated
//! valid files and files of any effects with any numbers never panic; each either loads as a
//! model that keeps every rule of `docs/discrepancy.md` §5 and saves and loads back the same, or
//! is refused with a `ModelFileError` of one line.
//!
//! The default case count keeps `cargo test` fast; for a long run:
//! `PROPTEST_CASES=100000 cargo test --release --lib grid::effect::fuzz`.

use std::path::Path;

use proptest::prelude::*;

use super::{EffectRecord, ModelFile, ModelFileError, MODEL_FORMAT};
use crate::protocol::fuzz::{self, near, text_properties, toml_token};

/// Pieces of TOML and of model files, the kind of thing a mutation should insert.
fn token() -> BoxedStrategy<String> {
    prop_oneof![
        toml_token(),
        Just("\"hgcd-model/1\"".to_string()),
        Just("[effect]\n".to_string()),
        Just("[[effects]]\n".to_string()),
        Just("name = \"none\"\n".to_string()),
        Just("name = \"payload\"\n".to_string()),
        Just("name = \"spring\"\n".to_string()),
        Just("mass_kg = 0.1\n".to_string()),
        Just("rotation_axis = [0, 1, 0]\n".to_string()),
        Just("anchor_m = [0, 0]\n".to_string()),
    ]
    .boxed()
}

/// Every effect, with values mostly in range.
fn effect() -> impl Strategy<Value = EffectRecord> {
    let triple = || [near(-1.0..1.0), near(-1.0..1.0), near(-1.0..1.0)];
    prop_oneof![
        Just(EffectRecord::None),
        near(-1.0..1.0).prop_map(|mass_kg| EffectRecord::Payload { mass_kg }),
        near(0.0..10.0).prop_map(|force_n| EffectRecord::CoulombFriction { force_n }),
        near(0.0..100.0)
            .prop_map(|damping_n_s_per_m| EffectRecord::ViscousDamping { damping_n_s_per_m }),
        near(0.0..0.1).prop_map(|delay_s| EffectRecord::TimeDelay { delay_s }),
        (near(0.0..0.5), triple(), any::<bool>()).prop_map(|(angle_rad, axis, unit)| {
            let norm = nalgebra::Vector3::from(axis).norm();
            let rotation_axis = if unit { axis.map(|c| c / norm) } else { axis };
            EffectRecord::GravityTilt {
                angle_rad,
                rotation_axis,
            }
        }),
        (near(-1000.0..10_000.0), triple()).prop_map(|(stiffness_n_per_m, anchor_m)| {
            EffectRecord::Spring {
                stiffness_n_per_m,
                anchor_m,
            }
        }),
    ]
}

/// The file's text, as `ModelFile::save` writes it.
fn text_of(file: &ModelFile) -> String {
    toml::to_string(file).expect("a model file serialises")
}

/// Valid files: one effect, none, and every effect at once.
fn valid_text() -> impl Strategy<Value = String> {
    let spring = EffectRecord::Spring {
        stiffness_n_per_m: 50.0,
        anchor_m: [0.01, 0.0, -0.02],
    };
    let every = vec![
        EffectRecord::GravityTilt {
            angle_rad: 0.05,
            rotation_axis: [0.0, 1.0, 0.0],
        },
        spring.clone(),
        EffectRecord::Payload { mass_kg: 0.02 },
        EffectRecord::CoulombFriction { force_n: 0.04 },
        EffectRecord::ViscousDamping {
            damping_n_s_per_m: 0.5,
        },
        EffectRecord::TimeDelay { delay_s: 0.004 },
    ];
    let file = |effect: EffectRecord, effects| {
        text_of(&ModelFile {
            format: MODEL_FORMAT.into(),
            grid: "grid.toml".into(),
            effect,
            effects,
        })
    };
    prop::sample::select(vec![
        file(spring, vec![]),
        file(EffectRecord::None, vec![]),
        file(every[0].clone(), every),
    ])
}

/// What every outcome of the parser must satisfy.
fn loads_soundly_or_is_refused_in_one_line(text: &str) -> Result<(), TestCaseError> {
    let path = Path::new("model.toml");
    match ModelFile::parse(text, path) {
        Err(e) => {
            let message = e.to_string();
            prop_assert!(!message.contains('\n'), "{message:?}");
            prop_assert!(matches!(e, ModelFileError::Invalid { .. }), "{message}");
        }
        Ok(file) => {
            prop_assert_eq!(&file.format, MODEL_FORMAT);
            for effect in file.all_effects() {
                prop_assert_eq!(effect.check(), Ok(()));
            }
            if let Some(first) = file.effects.first() {
                prop_assert_eq!(first, &file.effect);
            }
            for (i, e) in file.effects.iter().enumerate() {
                prop_assert!(*e != EffectRecord::None);
                prop_assert!(file.effects[..i].iter().all(|o| o.name() != e.name()));
            }
            let text = text_of(&file);
            let again = ModelFile::parse(&text, path)
                .map_err(|e| TestCaseError::fail(format!("{e}\n{text}")))?;
            prop_assert_eq!(again, file);
        }
    }
    Ok(())
}

text_properties!(
    fuzz::cases(1024),
    loads_soundly_or_is_refused_in_one_line,
    token,
    valid_text()
);

proptest! {
    #![proptest_config(fuzz::cases(1024))]

    #[test]
    fn files_of_any_effects_never_panic(
        effect in effect(), effects in proptest::collection::vec(effect(), 0..4),
        first in any::<bool>(),
    ) {
        let effect = match effects.first() {
            Some(e) if first => e.clone(),
            _ => effect,
        };
        let file = ModelFile { format: MODEL_FORMAT.into(), grid: "g.toml".into(), effect, effects };
        loads_soundly_or_is_refused_in_one_line(&text_of(&file))?;
    }
}
