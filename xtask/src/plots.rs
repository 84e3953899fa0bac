//! Line plots for reports, written as SVG (for the web and documents) and PNG (for viewers
//! and chat), from one drawing routine. PNG text is rendered with the bundled DejaVu Sans
//! Mono (assets/fonts, Bitstream Vera licence), so no system fonts are needed.

use std::path::Path;
use std::sync::Once;

use anyhow::{Context, Result, anyhow};
use deform_learn::experiment::Series;
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::{FontStyle, register_font};

static FONT: Once = Once::new();

fn register() {
    FONT.call_once(|| {
        // The bytes are a valid TrueType font bundled with the sources.
        let _ = register_font(
            "sans-serif",
            FontStyle::Normal,
            include_bytes!("../../assets/fonts/DejaVuSansMono.ttf"),
        );
    });
}

/// Series as points, `log10` of the values with `log` (non-positive values left out).
type Points = Vec<(String, Vec<(f64, f64)>)>;

/// A line plot of named series against their index, written to `stem.svg` and `stem.png`
/// (each atomically: drawn to a temporary file, then renamed); with `log`, of the series'
/// base-10 logarithms. Nothing is written when no series has a point.
pub fn plot(
    stem: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    series: &[Series],
    log: bool,
) -> Result<()> {
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
        return Ok(());
    }
    let y_desc = if log {
        format!("log10 {y_label}")
    } else {
        y_label.to_owned()
    };
    register();
    let svg = stem.with_extension("svg");
    let tmp = stem.with_extension("svg.tmp");
    draw(
        SVGBackend::new(&tmp, (800, 500)).into_drawing_area(),
        title,
        x_label,
        &y_desc,
        &points,
    )?;
    std::fs::rename(&tmp, &svg).with_context(|| format!("writing {}", svg.display()))?;
    let png = stem.with_extension("png");
    let tmp = stem.with_extension("tmp.png");
    draw(
        BitMapBackend::new(&tmp, (800, 500)).into_drawing_area(),
        title,
        x_label,
        &y_desc,
        &points,
    )?;
    std::fs::rename(&tmp, &png).with_context(|| format!("writing {}", png.display()))
}

fn draw<DB: DrawingBackend>(
    root: DrawingArea<DB, Shift>,
    title: &str,
    x_label: &str,
    y_desc: &str,
    series: &Points,
) -> Result<()>
where
    DB::ErrorType: 'static,
{
    let err = |e: DrawingAreaErrorKind<DB::ErrorType>| anyhow!("plot {title}: {e}");
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
    // Eight distinguishable colours (Okabe-Ito), so a policy comparison does not repeat one.
    let colors = [
        RGBColor(0, 114, 178),
        RGBColor(213, 94, 0),
        RGBColor(0, 158, 115),
        RGBColor(204, 121, 167),
        RGBColor(86, 180, 233),
        RGBColor(230, 159, 0),
        RGBColor(0, 0, 0),
        RGBColor(240, 228, 66),
    ];
    for (k, (name, points)) in series.iter().enumerate() {
        let color = colors[k % colors.len()];
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
