//! The apparent-mass grid: vertices of a cubic lattice with a mass at each, trilinear interpolation
//! between them, and the `hgcd-grid/1` file format (`docs/grid-format.md`).

use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};

use nalgebra::Vector3;
use thiserror::Error;

/// Format tag of version 1 grid files.
pub const GRID_FORMAT: &str = "hgcd-grid/1";
/// How far a gravity direction's norm may stray from 1 before it is rejected.
const UNIT_TOLERANCE: f64 = 1e-3;
/// Largest grid file read, bytes.
const MAX_FILE_BYTES: u64 = 64 << 20;
/// Largest number of vertices a grid file may hold (keeps hostile files from exhausting memory).
const MAX_VERTICES: usize = 1_000_000;

/// Why a grid could not be loaded, built or saved.
#[derive(Debug, Error)]
pub enum GridError {
    #[error("cannot read grid file {path}: {error}")]
    Read {
        path: PathBuf,
        error: std::io::Error,
    },
    #[error("grid file {path} is not valid TOML: {message}")]
    Syntax { path: PathBuf, message: String },
    #[error("grid file {path}: {message}")]
    Invalid { path: PathBuf, message: String },
    #[error("cannot write grid file {path}: {error}")]
    Write {
        path: PathBuf,
        error: std::io::Error,
    },
}

/// Apparent mass M(X) sampled on a cubic lattice, with the gravity direction it was measured along.
#[derive(Clone, Debug, PartialEq)]
pub struct MassGrid {
    /// Gravitational acceleration the masses are relative to, m/s².
    pub g: f64,
    /// Unit v_G: the direction of the compensating force (opposite to gravity).
    pub gravity_direction: Vector3<f64>,
    /// Position of the vertex with the smallest coordinates, m.
    pub origin: Vector3<f64>,
    /// Cube side L, m.
    pub spacing: f64,
    /// Vertices along x, y, z.
    pub dims: [usize; 3],
    /// Apparent mass at each vertex, kg, x fastest: index i + nx·(j + ny·k).
    pub masses: Vec<f64>,
    /// Keys beyond the required ones, kept as read and written back unchanged.
    pub extra: toml::Table,
}

/// Trilinear weights of the eight vertices of one cell: (vertex indices, weights).
pub type CellWeights = ([usize; 8], [f64; 8]);

impl MassGrid {
    /// A grid with the same mass everywhere (useful as a simulator field or a first guess).
    pub fn uniform(
        mass: f64,
        g: f64,
        gravity_direction: Vector3<f64>,
        origin: Vector3<f64>,
        spacing: f64,
        dims: [usize; 3],
    ) -> Self {
        let n = dims.iter().product();
        Self {
            g,
            gravity_direction: gravity_direction.normalize(),
            origin,
            spacing,
            dims,
            masses: vec![mass; n],
            extra: toml::Table::new(),
        }
    }

    /// Flat index of vertex (i, j, k).
    pub fn index(&self, i: usize, j: usize, k: usize) -> usize {
        i + self.dims[0] * (j + self.dims[1] * k)
    }

    /// Position of vertex (i, j, k), m.
    pub fn vertex_position(&self, i: usize, j: usize, k: usize) -> Vector3<f64> {
        self.origin + Vector3::new(i as f64, j as f64, k as f64) * self.spacing
    }

    /// Position of the vertex with the largest coordinates, m.
    pub fn far_corner(&self) -> Vector3<f64> {
        self.vertex_position(self.dims[0] - 1, self.dims[1] - 1, self.dims[2] - 1)
    }

    /// Whether `x` lies inside the grid's bounding box (faces included).
    pub fn contains(&self, x: &Vector3<f64>) -> bool {
        let far = self.far_corner();
        (0..3).all(|a| x[a] >= self.origin[a] && x[a] <= far[a])
    }

    /// Trilinear weights for `x`. Outside the grid the position is clamped onto it, so the nearest
    /// cell's face values hold. Coefficients are normalised: b = (x − x_k)/L, a = 1 − b (the paper's
    /// Section 4 writes (L − b)/L, which mixes units).
    pub fn cell_weights(&self, x: &Vector3<f64>) -> CellWeights {
        let mut base = [0usize; 3];
        let mut frac = [0f64; 3];
        for a in 0..3 {
            let cells = self.dims[a] - 1;
            if cells == 0 {
                continue;
            }
            let u = ((x[a] - self.origin[a]) / self.spacing).clamp(0.0, cells as f64);
            let cell = (u.floor() as usize).min(cells - 1);
            base[a] = cell;
            frac[a] = u - cell as f64;
        }
        let step = [
            usize::from(self.dims[0] > 1),
            usize::from(self.dims[1] > 1),
            usize::from(self.dims[2] > 1),
        ];
        let (b, d, f) = (frac[0], frac[1], frac[2]);
        let (a, c, e) = (1.0 - b, 1.0 - d, 1.0 - f);
        let mut idx = [0usize; 8];
        let mut w = [0f64; 8];
        // Vertex n has offsets (n & 1, (n >> 1) & 1, (n >> 2) & 1): the paper's M_0 … M_7.
        for n in 0..8 {
            let (ox, oy, oz) = (n & 1, (n >> 1) & 1, (n >> 2) & 1);
            idx[n] = self.index(
                base[0] + ox * step[0],
                base[1] + oy * step[1],
                base[2] + oz * step[2],
            );
            w[n] = [a, b][ox] * [c, d][oy] * [e, f][oz];
        }
        (idx, w)
    }

    /// Apparent mass at `x`, kg, trilinearly interpolated (nearest cell held outside the grid).
    pub fn mass_at(&self, x: &Vector3<f64>) -> f64 {
        let (idx, w) = self.cell_weights(x);
        (0..8).map(|n| w[n] * self.masses[idx[n]]).sum()
    }

    /// Compensating force M(X) g v_G at `x`, N.
    pub fn gravity_force(&self, x: &Vector3<f64>) -> Vector3<f64> {
        self.gravity_direction * (self.mass_at(x) * self.g)
    }

    /// Parse a grid from TOML text; `origin` names the source in messages.
    pub fn from_toml_str(text: &str, origin: &Path) -> Result<Self, GridError> {
        let invalid = |message: String| GridError::Invalid {
            path: origin.to_path_buf(),
            message,
        };
        let mut table: toml::Table =
            text.parse()
                .map_err(|e: toml::de::Error| GridError::Syntax {
                    path: origin.to_path_buf(),
                    message: e.message().to_string(),
                })?;
        let mut take = |key: &str| {
            table
                .remove(key)
                .ok_or_else(|| invalid(format!("missing required key `{key}`")))
        };
        let format = take("format")?;
        if format.as_str() != Some(GRID_FORMAT) {
            return Err(invalid(format!(
                "`format` is {format}, expected \"{GRID_FORMAT}\" (not an hgcd grid, or a newer version)"
            )));
        }
        let g = number(&take("g")?, "g").map_err(&invalid)?;
        let gravity_direction =
            vector(&take("gravity_direction")?, "gravity_direction").map_err(&invalid)?;
        let origin_v = vector(&take("origin")?, "origin").map_err(&invalid)?;
        let spacing = number(&take("spacing")?, "spacing").map_err(&invalid)?;
        let dims_v = take("dims")?;
        let masses_v = take("masses")?;

        if !(g.is_finite() && g > 0.0) {
            return Err(invalid(format!(
                "`g` must be a positive number of m/s², got {g}"
            )));
        }
        let norm = gravity_direction.norm();
        if !norm.is_finite() || (norm - 1.0).abs() > UNIT_TOLERANCE {
            return Err(invalid(format!(
                "`gravity_direction` must be a unit vector, its norm is {norm}"
            )));
        }
        if !(spacing.is_finite() && spacing > 0.0) {
            return Err(invalid(format!(
                "`spacing` must be a positive length in m, got {spacing}"
            )));
        }
        let dims_list = dims_v
            .as_array()
            .filter(|a| a.len() == 3)
            .ok_or_else(|| invalid("`dims` must be an array of three integers".into()))?;
        let mut dims = [0usize; 3];
        for (a, v) in dims_list.iter().enumerate() {
            dims[a] = v
                .as_integer()
                .filter(|&n| (1..=1000).contains(&n))
                .ok_or_else(|| {
                    invalid(format!(
                        "`dims` entries must be integers from 1 to 1000, got {v}"
                    ))
                })? as usize;
        }
        let count: usize = dims.iter().product();
        if count > MAX_VERTICES {
            return Err(invalid(format!(
                "grid has {count} vertices, at most {MAX_VERTICES} are supported"
            )));
        }
        let masses_list = masses_v
            .as_array()
            .ok_or_else(|| invalid("`masses` must be an array of numbers (kg)".into()))?;
        if masses_list.len() != count {
            return Err(invalid(format!(
                "`masses` has {} values but dims {:?} need {count}",
                masses_list.len(),
                dims
            )));
        }
        let mut masses = Vec::with_capacity(count);
        for (n, v) in masses_list.iter().enumerate() {
            let m = number(v, "masses").map_err(&invalid)?;
            if !(m.is_finite() && m > 0.0) {
                return Err(invalid(format!(
                    "mass at vertex {n} must be a positive number of kg, got {m}"
                )));
            }
            masses.push(m);
        }
        if !origin_v.iter().all(|c| c.is_finite()) {
            return Err(invalid("`origin` must be finite".into()));
        }
        Ok(Self {
            g,
            gravity_direction: gravity_direction / norm,
            origin: origin_v,
            spacing,
            dims,
            masses,
            extra: table,
        })
    }

    /// Load and validate a grid file (at most 64 MiB).
    pub fn load(path: &Path) -> Result<Self, GridError> {
        let read_err = |error| GridError::Read {
            path: path.to_path_buf(),
            error,
        };
        let size = fs::metadata(path).map_err(read_err)?.len();
        if size > MAX_FILE_BYTES {
            return Err(GridError::Invalid {
                path: path.to_path_buf(),
                message: format!("file is {size} bytes; a grid file is at most {MAX_FILE_BYTES}"),
            });
        }
        let text = fs::read_to_string(path).map_err(read_err)?;
        Self::from_toml_str(&text, path)
    }

    /// Render as `hgcd-grid/1` TOML: the required keys first, then the extra keys.
    pub fn to_toml_string(&self) -> String {
        let mut out = String::new();
        out.push_str(&format!("format = \"{GRID_FORMAT}\"\n"));
        out.push_str(&format!("g = {:?}\n", self.g));
        out.push_str(&format!(
            "gravity_direction = {}\n",
            fmt_vec(&self.gravity_direction)
        ));
        out.push_str(&format!("origin = {}\n", fmt_vec(&self.origin)));
        out.push_str(&format!("spacing = {:?}\n", self.spacing));
        out.push_str(&format!(
            "dims = [{}, {}, {}]\n",
            self.dims[0], self.dims[1], self.dims[2]
        ));
        out.push_str("masses = [\n");
        for chunk in self.masses.chunks(self.dims[0].max(1)) {
            let row: Vec<String> = chunk.iter().map(|m| format!("{m:?}")).collect();
            out.push_str(&format!("  {},\n", row.join(", ")));
        }
        out.push_str("]\n");
        if !self.extra.is_empty() {
            out.push('\n');
            // A toml::Table always serialises; the fallback only keeps the type honest.
            match toml::to_string(&self.extra) {
                Ok(text) => out.push_str(&text),
                Err(e) => out.push_str(&format!("# extra keys could not be written: {e}\n")),
            }
        }
        out
    }

    /// Write atomically: temporary file in the same directory, fsync, rename over `path`, fsync of
    /// the directory. An existing file at `path` is first kept as `path.bak`. On any error nothing
    /// at `path` has changed and the temporary file is removed.
    pub fn save_atomic(&self, path: &Path) -> Result<(), GridError> {
        let werr = |error| GridError::Write {
            path: path.to_path_buf(),
            error,
        };
        let dir = match path.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
            _ => PathBuf::from("."),
        };
        let name = path
            .file_name()
            .ok_or_else(|| werr(std::io::Error::other("not a file path")))?
            .to_string_lossy()
            .into_owned();
        let tmp = dir.join(format!(".{name}.tmp{}", std::process::id()));
        let result = (|| {
            let mut file = fs::File::create(&tmp)?;
            file.write_all(self.to_toml_string().as_bytes())?;
            file.sync_all()?;
            drop(file);
            if path.exists() {
                let backup = dir.join(format!("{name}.bak"));
                fs::copy(path, &backup)?;
                fs::File::open(&backup)?.sync_all()?;
            }
            fs::rename(&tmp, path)?;
            fs::File::open(&dir)?.sync_all()
        })();
        if result.is_err() {
            let _ = fs::remove_file(&tmp);
        }
        result.map_err(werr)
    }
}

fn fmt_vec(v: &Vector3<f64>) -> String {
    format!("[{:?}, {:?}, {:?}]", v.x, v.y, v.z)
}

fn number(v: &toml::Value, key: &str) -> Result<f64, String> {
    match v {
        toml::Value::Float(f) => Ok(*f),
        toml::Value::Integer(i) => Ok(*i as f64),
        other => Err(format!("`{key}` must be a number, got {other}")),
    }
}

fn vector(v: &toml::Value, key: &str) -> Result<Vector3<f64>, String> {
    let a = v
        .as_array()
        .filter(|a| a.len() == 3)
        .ok_or_else(|| format!("`{key}` must be an array of three numbers"))?;
    Ok(Vector3::new(
        number(&a[0], key)?,
        number(&a[1], key)?,
        number(&a[2], key)?,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn sample() -> MassGrid {
        let mut g = MassGrid::uniform(
            0.1,
            9.81,
            Vector3::z(),
            Vector3::new(-0.04, -0.04, -0.04),
            0.04,
            [3, 3, 3],
        );
        for k in 0..3 {
            for j in 0..3 {
                for i in 0..3 {
                    let n = g.index(i, j, k);
                    g.masses[n] = 0.05 + 0.01 * i as f64 + 0.02 * j as f64 + 0.04 * k as f64;
                }
            }
        }
        g
    }

    #[test]
    fn interpolation_hits_vertices_and_is_exact_for_affine_fields() {
        let g = sample();
        for k in 0..3 {
            for j in 0..3 {
                for i in 0..3 {
                    let x = g.vertex_position(i, j, k);
                    assert!((g.mass_at(&x) - g.masses[g.index(i, j, k)]).abs() < 1e-12);
                }
            }
        }
        // The field is affine in (i, j, k), so trilinear interpolation reproduces it everywhere.
        let x = Vector3::new(0.013, -0.027, 0.031);
        let u = (x - g.origin) / g.spacing;
        let expected = 0.05 + 0.01 * u.x + 0.02 * u.y + 0.04 * u.z;
        assert!((g.mass_at(&x) - expected).abs() < 1e-12);
    }

    #[test]
    fn interpolation_matches_the_paper_formula_in_one_cell() {
        let mut g = sample();
        // Make the field non-affine so the cross terms matter.
        for (n, m) in g.masses.iter_mut().enumerate() {
            *m = 0.05 + ((n * 7919) % 23) as f64 * 0.01;
        }
        let x = Vector3::new(0.011, 0.002, -0.035);
        let (xk, yk, zk) = (0.0, 0.0, -0.04);
        let l = 0.04;
        let (b, d, f) = ((x.x - xk) / l, (x.y - yk) / l, (x.z - zk) / l);
        let (a, c, e) = (1.0 - b, 1.0 - d, 1.0 - f);
        let m = |i, j, k| g.masses[g.index(i, j, k)];
        let expected = e * c * a * m(1, 1, 0)
            + e * c * b * m(2, 1, 0)
            + e * d * a * m(1, 2, 0)
            + e * d * b * m(2, 2, 0)
            + f * c * a * m(1, 1, 1)
            + f * c * b * m(2, 1, 1)
            + f * d * a * m(1, 2, 1)
            + f * d * b * m(2, 2, 1);
        assert!((g.mass_at(&x) - expected).abs() < 1e-12);
    }

    #[test]
    fn outside_the_grid_the_nearest_face_holds() {
        let g = sample();
        let inside = Vector3::new(0.04, 0.01, -0.02);
        let outside = Vector3::new(0.09, 0.01, -0.02);
        assert!((g.mass_at(&inside) - g.mass_at(&outside)).abs() < 1e-12);
    }

    #[test]
    fn toml_round_trip_keeps_extra_keys() {
        let mut g = sample();
        g.extra.insert(
            "device_id".into(),
            toml::Value::String("sim-point-mass".into()),
        );
        let text = g.to_toml_string();
        let back = MassGrid::from_toml_str(&text, Path::new("t.toml")).unwrap();
        assert_eq!(back, g);
    }

    #[test]
    fn rejects_bad_files_with_named_keys() {
        let good = sample().to_toml_string();
        let cases = [
            (good.replace("hgcd-grid/1", "hgcd-grid/9"), "format"),
            (
                good.replace("dims = [3, 3, 3]", "dims = [3, 3, 4]"),
                "masses",
            ),
            (
                good.replace(
                    "gravity_direction = [0.0, 0.0, 1.0]",
                    "gravity_direction = [0.0, 0.0, 2.0]",
                ),
                "unit vector",
            ),
            (good.replace("0.05, ", "-0.05, "), "positive"),
            (good.replace("0.05, ", "nan, "), "positive"),
            (good.replace("spacing = 0.04", ""), "spacing"),
            ("format = ".to_string(), "TOML"),
        ];
        for (text, needle) in cases {
            let err = MassGrid::from_toml_str(&text, Path::new("x.toml"))
                .unwrap_err()
                .to_string();
            assert!(err.contains(needle), "{err:?} should mention {needle}");
        }
    }

    #[test]
    fn atomic_save_keeps_a_backup() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("dev.toml");
        let mut g = sample();
        g.save_atomic(&path).unwrap();
        g.masses[0] = 0.2;
        g.save_atomic(&path).unwrap();
        assert_eq!(MassGrid::load(&path).unwrap().masses[0], 0.2);
        assert_eq!(
            MassGrid::load(&dir.path().join("dev.toml.bak"))
                .unwrap()
                .masses[0],
            0.05
        );
        let leftovers: Vec<_> = fs::read_dir(dir.path()).unwrap().collect();
        assert_eq!(leftovers.len(), 2);
    }

    proptest! {
        #[test]
        fn arbitrary_text_never_panics(text in ".{0,400}") {
            let _ = MassGrid::from_toml_str(&text, Path::new("p.toml"));
        }

        #[test]
        fn arbitrary_values_in_valid_shape_never_panic(
            g in any::<f64>(), dx in any::<f64>(), spacing in any::<f64>(),
            nx in -2i64..5, masses in proptest::collection::vec(any::<f64>(), 0..10)
        ) {
            let text = format!(
                "format = \"hgcd-grid/1\"\ng = {g:?}\ngravity_direction = [{dx:?}, 0.0, 1.0]\n\
                 origin = [0.0, 0.0, 0.0]\nspacing = {spacing:?}\ndims = [{nx}, 1, 1]\nmasses = {masses:?}\n"
            ).replace("NaN", "nan");
            if let Ok(grid) = MassGrid::from_toml_str(&text, Path::new("p.toml")) {
                let m = grid.mass_at(&Vector3::new(dx, spacing, g));
                prop_assert!(m.is_finite() || !dx.is_finite() || !spacing.is_finite() || !g.is_finite());
            }
        }
    }
}
