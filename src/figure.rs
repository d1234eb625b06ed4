//! Figures in SVG and PNG without system libraries: plotters' SVG and bitmap backends, with
//! text in the embedded DejaVu Sans subset (assets/fonts/). `hgcd validate` and `hgcd analyze`
//! draw through [`draw`], into a directory [`check_out_dir`] checked first.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::{register_font, FontStyle};
use thiserror::Error;

/// The embedded font (a subset of DejaVu Sans; licence in assets/fonts/LICENSE).
static FONT: &[u8] = include_bytes!("../assets/fonts/DejaVuSans-subset.ttf");

#[derive(Debug, Error)]
#[error("drawing the figure {}: {message}", path.display())]
pub struct FigureError {
    pub path: PathBuf,
    pub message: String,
}

/// A command's results (figures and tables) cannot be written in its output directory (`--out`).
#[derive(Debug, Error)]
#[error("cannot write the results in {} (--out)", path.display())]
pub struct OutError {
    /// The directory, or the file that could not be written.
    pub path: PathBuf,
    #[source]
    pub source: std::io::Error,
}

/// Make `out`, the directory a command writes its figures and tables to (`hgcd validate --out`,
/// `hgcd analyze --out`), if needed, and check a file can be written there by writing and removing
/// `out/.hgcd-<command>-write-check`: an unwritable directory shows before the work starts.
///
/// Errors: [`OutError`] naming `out`.
pub fn check_out_dir(out: &Path, command: &str) -> Result<(), OutError> {
    let probe = out.join(format!(".hgcd-{command}-write-check"));
    (|| {
        std::fs::create_dir_all(out)?;
        std::fs::write(&probe, b"")?;
        std::fs::remove_file(&probe)
    })()
    .map_err(|source| OutError {
        path: out.to_path_buf(),
        source,
    })
}

/// Register the embedded font as plotters' "sans-serif", once per process.
fn font_registered() -> bool {
    static REGISTERED: OnceLock<bool> = OnceLock::new();
    *REGISTERED.get_or_init(|| register_font("sans-serif", FontStyle::Normal, FONT).is_ok())
}

/// A figure's drawing, for any backend.
pub trait Figure {
    fn plot<DB: DrawingBackend>(
        &self,
        root: &DrawingArea<DB, Shift>,
    ) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>>;
}

/// The legend both figures use: upper right, on a light box.
pub fn legend<'a, DB: DrawingBackend + 'a, CT: plotters::coord::CoordTranslate>(
    chart: &mut ChartContext<'a, DB, CT>,
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperRight)
        .background_style(WHITE.mix(0.9))
        .border_style(BLACK.mix(0.5))
        .label_font(("sans-serif", 14))
        .draw()
}

/// Draw `figure` of `size` px as SVG at `svg` and as PNG at `png`.
///
/// # Errors
/// [`FigureError`] naming the file that could not be drawn or written.
pub fn draw(
    figure: &impl Figure,
    size: (u32, u32),
    svg: &Path,
    png: &Path,
) -> Result<(), FigureError> {
    let err = |path: &Path| {
        let path = path.to_path_buf();
        move |e: &dyn std::fmt::Display| FigureError {
            path: path.clone(),
            message: e.to_string(),
        }
    };
    if !font_registered() {
        return Err(err(svg)(&"the embedded font does not load"));
    }
    let root = SVGBackend::new(svg, size).into_drawing_area();
    figure.plot(&root).map_err(|e| err(svg)(&e))?;
    root.present().map_err(|e| err(svg)(&e))?;
    let root = BitMapBackend::new(png, size).into_drawing_area();
    figure.plot(&root).map_err(|e| err(png)(&e))?;
    root.present().map_err(|e| err(png)(&e))?;
    Ok(())
}
