//! Line plots for reports, written as SVG (for the web and documents) and PNG (for viewers
//! and chat), from one drawing routine. PNG text is rendered with the bundled DejaVu Sans
//! Mono (assets/fonts, Bitstream Vera licence), so no system fonts are needed.

use std::path::Path;
use std::sync::Once;

use crate::error::{RenderError, Result};
use crate::{Plot, Series};
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::{FontStyle, register_font};

static FONT: Once = Once::new();

/// Pixels (PNG) or points (SVG).
const SIZE: (u32, u32) = (800, 500);

/// Eight distinguishable colours (Okabe-Ito), so a policy comparison does not repeat one.
const COLORS: [u32; 8] = [
    0x0072b2, 0xd55e00, 0x009e73, 0xcc79a7, 0x56b4e9, 0xe69f00, 0x000000, 0xf0e442,
];

fn register() {
    FONT.call_once(|| {
        // The bytes are a valid TrueType font bundled with the sources.
        let _ = register_font(
            "sans-serif",
            FontStyle::Normal,
            include_bytes!("../../../assets/fonts/DejaVuSansMono.ttf"),
        );
    });
}

/// Series as points, `log10` of the values with `log` (non-positive values left out).
type Points = Vec<(String, Vec<(f64, f64)>)>;

/// A line plot of named series against their index, written to `stem.svg` and `stem.png`
/// (each atomically: drawn to a temporary file, then renamed); with `log`, of the series'
/// base-10 logarithms. Nothing is written when no series has a point; returns whether the
/// files were written.
pub fn plot(stem: &Path, p: &Plot) -> Result<bool> {
    let (series, log) = (&p.series, p.log);
    let points: Points = series
        .iter()
        .map(|Series { name, values }| {
            let p = values
                .iter()
                .enumerate()
                .filter(|(_, y)| y.is_finite() && (!log || **y > 0.0))
                .map(|(i, y)| (i as f64, if log { y.log10() } else { *y }))
                .collect();
            (name.clone(), p)
        })
        .collect();
    if points.iter().all(|(_, p)| p.is_empty()) {
        return Ok(false);
    }
    let y_desc = if log {
        format!("log10 {}", p.y_label)
    } else {
        p.y_label.to_owned()
    };
    register();
    let labels = [p.title.as_str(), p.x_label, &y_desc];
    let (svg, svg_tmp) = (stem.with_extension("svg"), stem.with_extension("svg.tmp"));
    draw(
        SVGBackend::new(&svg_tmp, SIZE).into_drawing_area(),
        labels,
        &points,
    )?;
    let (png, png_tmp) = (stem.with_extension("png"), stem.with_extension("tmp.png"));
    draw(
        BitMapBackend::new(&png_tmp, SIZE).into_drawing_area(),
        labels,
        &points,
    )?;
    for (tmp, path) in [(svg_tmp, svg), (png_tmp, png)] {
        std::fs::rename(&tmp, &path).map_err(|source| RenderError::Io { path, source })?;
    }
    Ok(true)
}

fn draw<DB: DrawingBackend>(
    root: DrawingArea<DB, Shift>,
    [title, x_label, y_desc]: [&str; 3],
    series: &Points,
) -> Result<()>
where
    DB::ErrorType: 'static,
{
    let err = |e: DrawingAreaErrorKind<DB::ErrorType>| RenderError::Plot {
        title: title.to_owned(),
        reason: e.to_string(),
    };
    let ys = series.iter().flat_map(|(_, p)| p.iter().map(|q| q.1));
    let (lo, hi) = ys.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
        (a.min(v), b.max(v))
    });
    let pad = 0.05 * (hi - lo).max(1e-30);
    let len = series
        .iter()
        .map(|(_, p)| p.len())
        .max()
        .unwrap_or(1)
        .max(2);
    root.fill(&WHITE).map_err(err)?;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 22))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(70)
        .build_cartesian_2d(0f64..(len - 1) as f64, (lo - pad)..(hi + pad))
        .map_err(err)?;
    chart
        .configure_mesh()
        .x_desc(x_label)
        .y_desc(y_desc)
        .draw()
        .map_err(err)?;
    for (k, (name, points)) in series.iter().enumerate() {
        let c = COLORS[k % COLORS.len()];
        let color = RGBColor((c >> 16) as u8, (c >> 8) as u8, c as u8);
        chart
            .draw_series(LineSeries::new(
                points.iter().copied(),
                color.stroke_width(2),
            ))
            .map_err(err)?
            .label(name.as_str())
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2))
            });
    }
    chart
        .configure_series_labels()
        .border_style(BLACK)
        .background_style(WHITE)
        .draw()
        .map_err(err)?;
    root.present().map_err(err)?;
    Ok(())
}
