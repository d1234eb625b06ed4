//! The paper's Fig. 2 for one device: the mean penalty at each contact point with its standard
//! deviation as an error bar, one line per compensation mode, and the ideal m_p g / k as a dashed
//! line ([`crate::figure`]).

use std::path::Path;

use plotters::coord::Shift;
use plotters::prelude::*;

use super::report::Report;
use super::Mode;
use crate::figure::{Figure, FigureError};

/// Figure size, px.
const SIZE: (u32, u32) = (1100, 620);

/// Colour and line style of a mode: the paper's blue dotted line without compensation, red solid
/// with it; the vector mode in green.
fn colour(mode: Mode) -> RGBColor {
    match mode {
        Mode::None => RGBColor(31, 119, 180),
        Mode::Scalar => RGBColor(214, 39, 40),
        Mode::Vector => RGBColor(44, 160, 44),
        Mode::Arm => RGBColor(148, 103, 189),
    }
}

/// Draw the figure as SVG at `svg` and PNG at `png`.
pub fn draw(report: &Report, svg: &Path, png: &Path) -> Result<(), FigureError> {
    crate::figure::draw(&Penalties(report), SIZE, svg, png)
}

struct Penalties<'a>(&'a Report);

impl Figure for Penalties<'_> {
    fn plot<DB: DrawingBackend>(
        &self,
        root: &DrawingArea<DB, Shift>,
    ) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
        plot(self.0, root)
    }
}

fn plot<DB: DrawingBackend>(
    report: &Report,
    root: &DrawingArea<DB, Shift>,
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    root.fill(&WHITE)?;
    let mm = |v: f64| v * 1e3;
    let top = report
        .modes
        .iter()
        .flat_map(|m| m.two_sided.points.iter())
        .map(|s| mm(s.mean + s.std))
        .filter(|v| v.is_finite())
        .fold(mm(report.ideal) * 1.5, f64::max)
        // Head room for the legend.
        * 1.35;
    let n = report.points.len();
    let mut chart = ChartBuilder::on(root)
        .caption(
            format!(
                "Penalty ΔX per contact point on {} (probe {:.0} g, k = {} N/mm, {} repetitions)",
                report.device,
                report.probe_mass * 1e3,
                report.stiffness * 1e-3,
                report.repetitions
            ),
            ("sans-serif", 20),
        )
        .margin(15)
        .x_label_area_size(55)
        .y_label_area_size(65)
        .build_cartesian_2d(0.5f64..n as f64 + 0.5, 0f64..top)?;
    chart
        .configure_mesh()
        .x_labels(n)
        .x_label_formatter(&|x| format!("{}", x.round() as i64))
        .y_label_formatter(&|y| format!("{y:.2}"))
        .x_desc(
            "contact point n  (P_n = centre + spacing·(i, j, k), n = 1 + (i+1) + 3(j+1) + 9(k+1))",
        )
        .y_desc("penalty ΔX, mm")
        .label_style(("sans-serif", 14))
        .axis_desc_style(("sans-serif", 15))
        .light_line_style(WHITE.mix(0.0))
        .draw()?;

    let ideal = mm(report.ideal);
    chart
        .draw_series(DashedLineSeries::new(
            [(0.5, ideal), (n as f64 + 0.5, ideal)],
            8,
            5,
            BLACK.stroke_width(2),
        ))?
        .label(format!("ideal m_p g / k = {ideal:.3} mm"))
        .legend(|(x, y)| PathElement::new([(x, y), (x + 20, y)], BLACK.stroke_width(2)));

    let runs = report.modes.len() as f64;
    for (r, m) in report.modes.iter().enumerate() {
        let colour = colour(m.mode);
        // Side by side at each point, so the error bars do not hide each other.
        let shift = (r as f64 - (runs - 1.0) / 2.0) * 0.15;
        let points: Vec<(f64, f64, f64)> = m
            .two_sided
            .points
            .iter()
            .enumerate()
            .filter(|(_, s)| s.mean.is_finite())
            .map(|(k, s)| ((k + 1) as f64 + shift, mm(s.mean), mm(s.std)))
            .collect();
        let line: Vec<(f64, f64)> = points.iter().map(|&(x, y, _)| (x, y)).collect();
        let label = format!("{}: mean {:.3} mm", m.mode.name(), mm(m.two_sided.mean));
        let style = colour.stroke_width(2);
        let series = if m.mode == Mode::None {
            chart.draw_series(DashedLineSeries::new(line.clone(), 4, 4, style))?
        } else {
            chart.draw_series(LineSeries::new(line.clone(), style))?
        };
        series
            .label(label)
            .legend(move |(x, y)| PathElement::new([(x, y), (x + 20, y)], colour.stroke_width(2)));
        chart.draw_series(points.iter().map(|&(x, y, s)| {
            ErrorBar::new_vertical(x, y - s, y, y + s, colour.stroke_width(1), 6)
        }))?;
        chart.draw_series(
            line.iter()
                .map(|&(x, y)| Circle::new((x, y), 3, colour.filled())),
        )?;
    }
    crate::figure::legend(&mut chart)
}
