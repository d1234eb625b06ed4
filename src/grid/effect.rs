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

/// The range of each parameter of a model effect (docs/discrepancy.md §5): what a device with
/// a handle, not a fault, can show.
pub const MASS_RANGE: (f64, f64) = (-1.0, 1.0);
pub const FRICTION_RANGE: (f64, f64) = (0.0, 10.0);
pub const DAMPING_RANGE: (f64, f64) = (0.0, 100.0);
pub const DELAY_RANGE: (f64, f64) = (0.0, 0.1);
pub const TILT_RANGE: (f64, f64) = (0.0, 0.5);
pub const STIFFNESS_RANGE: (f64, f64) = (-1000.0, 10_000.0);
pub const ANCHOR_RANGE: (f64, f64) = (-10.0, 10.0);

impl EffectRecord {
    /// The effect's name, as the file and `hgcd analyze` write it.
    pub fn name(&self) -> &'static str {
        match self {
            EffectRecord::None => "none",
            EffectRecord::Payload { .. } => "payload",
            EffectRecord::CoulombFriction { .. } => "coulomb_friction",
            EffectRecord::ViscousDamping { .. } => "viscous_damping",
            EffectRecord::TimeDelay { .. } => "time_delay",
            EffectRecord::GravityTilt { .. } => "gravity_tilt",
            EffectRecord::Spring { .. } => "spring",
        }
    }

    /// Every parameter finite and in its range, a rotation axis of unit length.
    ///
    /// # Errors
    /// One line naming the effect, the key, the value and the range.
    pub fn check(&self) -> Result<(), String> {
        let name = self.name();
        let within = |key: &str, value: f64, (lo, hi): (f64, f64), unit: &str| {
            if value.is_finite() && (lo..=hi).contains(&value) {
                Ok(())
            } else {
                Err(format!(
                    "`{name}` `{key}` is {}, out of range ({lo} to {hi} {unit})",
                    crate::config::Number(value)
                ))
            }
        };
        match self {
            EffectRecord::None => Ok(()),
            EffectRecord::Payload { mass_kg } => within("mass_kg", *mass_kg, MASS_RANGE, "kg"),
            EffectRecord::CoulombFriction { force_n } => {
                within("force_n", *force_n, FRICTION_RANGE, "N")
            }
            EffectRecord::ViscousDamping { damping_n_s_per_m } => within(
                "damping_n_s_per_m",
                *damping_n_s_per_m,
                DAMPING_RANGE,
                "N*s/m",
            ),
            EffectRecord::TimeDelay { delay_s } => within("delay_s", *delay_s, DELAY_RANGE, "s"),
            EffectRecord::GravityTilt {
                angle_rad,
                rotation_axis,
            } => {
                within("angle_rad", *angle_rad, TILT_RANGE, "rad")?;
                let norm = nalgebra::Vector3::from(*rotation_axis).norm();
                if (norm - 1.0).abs() <= 1e-3 {
                    Ok(())
                } else {
                    Err(format!(
                        "`{name}` `rotation_axis` has length {norm}: expected a unit vector"
                    ))
                }
            }
            EffectRecord::Spring {
                stiffness_n_per_m,
                anchor_m,
            } => {
                within(
                    "stiffness_n_per_m",
                    *stiffness_n_per_m,
                    STIFFNESS_RANGE,
                    "N/m",
                )?;
                anchor_m
                    .iter()
                    .try_for_each(|a| within("anchor_m", *a, ANCHOR_RANGE, "m"))
            }
        }
    }
}

impl ModelFile {
    /// Read and check a model file.
    ///
    /// # Errors
    /// [`ModelFileError`]: unreadable, or as [`ModelFile::parse`].
    pub fn load(path: &Path) -> Result<Self, ModelFileError> {
        let text = crate::sys::read_text(path).map_err(|source| ModelFileError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        Self::parse(&text, path)
    }

    /// [`ModelFile::load`] on `text`, read from `path`.
    ///
    /// # Errors
    /// [`ModelFileError::Invalid`]: not TOML, not `hgcd-model/1`, an unknown effect, a parameter
    /// that is not finite or out of its range ([`EffectRecord::check`]), `[[effects]]` naming
    /// `none` or an effect twice, or not starting with `[effect]`.
    pub fn parse(text: &str, path: &Path) -> Result<Self, ModelFileError> {
        let invalid = |message: String| ModelFileError::Invalid {
            path: path.to_path_buf(),
            message,
        };
        let file: ModelFile =
            toml::from_str(text).map_err(|e| invalid(crate::config::toml_error(text, &e)))?;
        if file.format != MODEL_FORMAT {
            return Err(invalid(format!(
                "`format` is \"{}\", expected \"{MODEL_FORMAT}\"",
                file.format
            )));
        }
        for effect in file.all_effects() {
            effect.check().map_err(invalid)?;
        }
        for (i, effect) in file.effects.iter().enumerate() {
            let name = effect.name();
            if *effect == EffectRecord::None {
                return Err(invalid(
                    "`[[effects]]` lists `none`: it lists the effects found, each once".into(),
                ));
            }
            if file.effects[..i].iter().any(|e| e.name() == name) {
                return Err(invalid(format!(
                    "`[[effects]]` names `{name}` twice: it lists the effects found, each once"
                )));
            }
        }
        if file
            .effects
            .first()
            .is_some_and(|first| *first != file.effect)
        {
            return Err(invalid(
                "`[effect]` is not the first of `[[effects]]`: which one holds the model?".into(),
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
mod fuzz;

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
            ("format = \"hgcd-model/1\"\ngrid = \"g\"\n[effect]\nname = \"payload\"\nmass_kg = nan\n", "`payload` `mass_kg` is nan, out of range (-1 to 1 kg)"),
            // Issue 40: a spring of −1e6 N/m was accepted and pushed the handle at the limit.
            ("format = \"hgcd-model/1\"\ngrid = \"g\"\n[effect]\nname = \"spring\"\nstiffness_n_per_m = -1e6\nanchor_m = [0.0, 0.0, 0.0]\n", "`spring` `stiffness_n_per_m` is -1000000, out of range (-1000 to 10000 N/m)"),
            ("format = \"hgcd-model/1\"\ngrid = \"g\"\n[effect]\nname = \"spring\"\nstiffness_n_per_m = 10.0\nanchor_m = [0.0, 1e300, 0.0]\n", "`anchor_m` is 1e300"),
            ("format = \"hgcd-model/1\"\ngrid = \"g\"\n[effect]\nname = \"gravity_tilt\"\nangle_rad = 0.1\nrotation_axis = [0.0, 2.0, 0.0]\n", "expected a unit vector"),
            ("format = \"hgcd-model/1\"\ngrid = \"g\"\n[effect]\nname = \"time_delay\"\ndelay_s = -0.01\n", "`time_delay` `delay_s` is -0.01"),
            ("format = \"hgcd-model/1\"\ngrid = \"g\"\n[effect]\nname = \"none\"\n[[effects]]\nname = \"coulomb_friction\"\nforce_n = 1e9\n", "`coulomb_friction` `force_n` is 1e9"),
            // Issue 40 (fuzzing): a TOML error took several lines; an effect named twice (two
            // payloads add up beyond the range), `none` among the effects and an `[effect]`
            // other than the first of `[[effects]]` were accepted.
            ("format = \"hgcd-model/1\"\ngrid = \"g\"\n[effect\n", "line 3 (``): invalid table header"),
            ("format = \"hgcd-model/1\"\ngrid = \"g\"\n[effect]\nname = \"payload\"\nmass_kg = 0.9\n[[effects]]\nname = \"payload\"\nmass_kg = 0.9\n[[effects]]\nname = \"payload\"\nmass_kg = 0.9\n", "`[[effects]]` names `payload` twice"),
            ("format = \"hgcd-model/1\"\ngrid = \"g\"\n[effect]\nname = \"none\"\n[[effects]]\nname = \"none\"\n", "`[[effects]]` lists `none`"),
            ("format = \"hgcd-model/1\"\ngrid = \"g\"\n[effect]\nname = \"none\"\n[[effects]]\nname = \"payload\"\nmass_kg = 0.1\n", "`[effect]` is not the first of `[[effects]]`"),
        ] {
            std::fs::write(&path, bad).unwrap();
            let e = ModelFile::load(&path).unwrap_err().to_string();
            assert!(e.contains(says), "{e}");
            assert_eq!(e.lines().count(), 1, "{e}");
        }
    }
}
