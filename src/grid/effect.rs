//! `hgcd-model/1` (docs/discrepancy.md §5): the physical effect `hgcd analyze` found, beside the
//! grid it was measured against. `hgcd run` adds the effects that are forces of the position
//! alone (payload, gravity tilt, spring) to the grid's compensation (`compensation.effect_file`).

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use thiserror::Error;

/// The `format` key of a model file.
pub const MODEL_FORMAT: &str = "hgcd-model/1";

/// A model file: the grid (relative to the file) and the effects with their parameters, SI.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ModelFile {
    pub format: String,
    pub grid: PathBuf,
    /// The first effect named (`none` for none): what a reader of one effect sees.
    pub effect: EffectRecord,
    /// Every effect named, in the order found (the first is `effect`); absent in files of one
    /// effect.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub effects: Vec<EffectRecord>,
}

/// The effect, named as `hgcd analyze` names it; keys as in its summary.json (others ignored).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "name", rename_all = "snake_case")]
pub enum EffectRecord {
    None,
    Payload {
        mass_kg: f64,
    },
    CoulombFriction {
        force_n: f64,
    },
    ViscousDamping {
        damping_n_s_per_m: f64,
    },
    TimeDelay {
        delay_s: f64,
    },
    GravityTilt {
        angle_rad: f64,
        rotation_axis: [f64; 3],
    },
    Spring {
        stiffness_n_per_m: f64,
        anchor_m: [f64; 3],
    },
}

/// Why a model file cannot be used.
#[derive(Debug, Error)]
pub enum ModelFileError {
    #[error("cannot read the model file {}", path.display())]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("model file {}: {message}", path.display())]
    Invalid { path: PathBuf, message: String },
    #[error("cannot write the model file {}", path.display())]
    Write {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
}

impl ModelFile {
    /// Read and check a model file.
    ///
    /// # Errors
    /// [`ModelFileError`]: unreadable, not TOML, not `hgcd-model/1`, an unknown effect, or a
    /// parameter that is not finite.
    pub fn load(path: &Path) -> Result<Self, ModelFileError> {
        let invalid = |message: String| ModelFileError::Invalid {
            path: path.to_path_buf(),
            message,
        };
        let text = std::fs::read_to_string(path).map_err(|source| ModelFileError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        let file: ModelFile =
            toml::from_str(&text).map_err(|e| invalid(e.message().to_string()))?;
        if file.format != MODEL_FORMAT {
            return Err(invalid(format!(
                "`format` is \"{}\", expected \"{MODEL_FORMAT}\"",
                file.format
            )));
        }
        let values: Vec<f64> = file
            .all_effects()
            .iter()
            .flat_map(|e| match e {
                EffectRecord::None => vec![],
                EffectRecord::Payload { mass_kg } => vec![*mass_kg],
                EffectRecord::CoulombFriction { force_n } => vec![*force_n],
                EffectRecord::ViscousDamping { damping_n_s_per_m } => vec![*damping_n_s_per_m],
                EffectRecord::TimeDelay { delay_s } => vec![*delay_s],
                EffectRecord::GravityTilt {
                    angle_rad,
                    rotation_axis,
                } => [[*angle_rad].as_slice(), rotation_axis].concat(),
                EffectRecord::Spring {
                    stiffness_n_per_m,
                    anchor_m,
                } => [[*stiffness_n_per_m].as_slice(), anchor_m].concat(),
            })
            .collect();
        if values.iter().any(|v| !v.is_finite()) {
            return Err(invalid(
                "a parameter of `[effect]` is not a finite number".into(),
            ));
        }
        Ok(file)
    }

    /// Every effect the file holds: `effects`, or `effect` alone in a file of one.
    pub fn all_effects(&self) -> Vec<EffectRecord> {
        if self.effects.is_empty() {
            match self.effect {
                EffectRecord::None => vec![],
                ref one => vec![one.clone()],
            }
        } else {
            self.effects.clone()
        }
    }

    /// Write the file.
    ///
    /// # Errors
    /// [`ModelFileError::Write`].
    pub fn save(&self, path: &Path) -> Result<(), ModelFileError> {
        let mut text = String::from(
            "# The calibrated grid and the effects hgcd analyze added to it \
             (docs/discrepancy.md §5).\n",
        );
        text.push_str(&toml::to_string(self).expect("a model file serialises"));
        std::fs::write(path, text).map_err(|source| ModelFileError::Write {
            path: path.to_path_buf(),
            source,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_model_file_round_trips_and_bad_ones_say_why() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("model.toml");
        let file = ModelFile {
            format: MODEL_FORMAT.into(),
            grid: "grid.toml".into(),
            effect: EffectRecord::Spring {
                stiffness_n_per_m: 50.0,
                anchor_m: [0.01, 0.0, -0.02],
            },
            effects: vec![],
        };
        file.save(&path).unwrap();
        assert_eq!(ModelFile::load(&path).unwrap(), file);
        let text = std::fs::read_to_string(&path).unwrap();
        assert!(text.contains("name = \"spring\""), "{text}");
        for (bad, says) in [
            ("format = \"x\"\ngrid = \"g\"\n[effect]\nname = \"none\"\n", "expected \"hgcd-model/1\""),
            ("format = \"hgcd-model/1\"\ngrid = \"g\"\n[effect]\nname = \"magic\"\n", "unknown variant"),
            ("format = \"hgcd-model/1\"\ngrid = \"g\"\n[effect]\nname = \"payload\"\nmass_kg = nan\n", "not a finite"),
        ] {
            std::fs::write(&path, bad).unwrap();
            let e = ModelFile::load(&path).unwrap_err().to_string();
            assert!(e.contains(says), "{e}");
        }
    }
}
