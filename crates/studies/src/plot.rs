//! Line plots for reports, written as SVG (for the web and documents) and PNG (for viewers
//! and chat), from one drawing routine. PNG text is rendered with the bundled DejaVu Sans
//! (assets/fonts, Bitstream Vera licence), so no system fonts are needed; text is measured
//! with the same font. (A monospace font put a full cell around each `.`: `0. 09`.)
//!
//! Where everything goes is computed first ([`Layout`]): the title's font size so that it
//! fits, the legend in a column of its own right of the data (it never covers a line), the
//! y labels' room from the longest label. Tick labels are formatted here (no stray digits,
//! whole numbers on index axes), and a categorical axis names its categories.

use std::path::Path;
use std::sync::{LazyLock, Once};

use ab_glyph::{Font as _, FontRef, ScaleFont as _};

use crate::error::{RenderError, Result};
use crate::{Marks, Plot, Series};
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::{FontStyle, register_font};

static FONT: Once = Once::new();

/// Pixels (PNG) or points (SVG).
pub(crate) const SIZE: (u32, u32) = (960, 540);

/// Twelve distinguishable colours: Okabe-Ito's eight (yellow last), then four of Paul Tol's
/// muted scheme. Series past the sixth are also dashed, so print in grey still tells them
/// apart.
const COLORS: [u32; 12] = [
    0x0072b2, 0xd55e00, 0x009e73, 0xcc79a7, 0x56b4e9, 0xe69f00, 0x000000, 0x882255, 0x44aa99,
    0x332288, 0x999933, 0xc5a900,
];

/// The bundled font's bytes: the one text is drawn with and measured with.
const FONT_BYTES: &[u8] = include_bytes!("../../../assets/fonts/DejaVuSans.ttf");

static MEASURE: LazyLock<FontRef<'static>> =
    LazyLock::new(|| FontRef::try_from_slice(FONT_BYTES).expect("the bundled font parses"));

/// Font sizes: title (largest; shrunk to fit), axis descriptions, tick and legend labels.
const TITLE_SIZE: u32 = 22;
const MIN_TITLE_SIZE: u32 = 11;
const DESC_SIZE: u32 = 16;
const LABEL_SIZE: u32 = 13;

/// The widest legend column, and the widest y tick label, in pixels, before they are cut.
const MAX_LEGEND: u32 = 300;
const MAX_Y_LABEL: u32 = 240;

fn register() {
    FONT.call_once(|| {
        // The bytes are a valid TrueType font bundled with the sources.
        let _ = register_font("sans-serif", FontStyle::Normal, FONT_BYTES);
    });
}

/// The width in pixels of `text` at font `size`, as the bundled font sets it (5 % added
/// for the SVG viewer's own sans-serif font).
fn text_width(text: &str, size: u32) -> u32 {
    let font = MEASURE.as_scaled(size as f32);
    let width: f32 = text.chars().map(|c| font.h_advance(font.glyph_id(c))).sum();
    (1.05 * width).ceil() as u32
}

/// `text` cut to fit `width` pixels at font `size`, ending in `...` when cut.
fn cut(text: &str, size: u32, width: u32) -> String {
    if text_width(text, size) <= width {
        return text.to_owned();
    }
    let mut kept: Vec<char> = text.chars().collect();
    while !kept.is_empty() && text_width(&format!("{}...", String::from_iter(&kept)), size) > width
    {
        kept.pop();
    }
    format!("{}...", String::from_iter(&kept))
}

/// Where a plot's parts go, in pixels of a [`SIZE`] canvas.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Layout {
    /// The title's font size (the largest up to [`TITLE_SIZE`] at which it fits).
    pub title_size: u32,
    /// The title as drawn: cut, ending in `...`, when it does not fit even at
    /// [`MIN_TITLE_SIZE`].
    pub title: String,
    /// The legend's column at the right: its left edge (the data end before it).
    pub legend_left: u32,
    /// The legend's entries as drawn (cut to the column).
    pub legend: Vec<String>,
    /// Room left of the data for the y tick labels and the axis description.
    pub y_label_area: u32,
    /// Room below the data for the x tick labels and the axis description.
    pub x_label_area: u32,
    /// The margin around the chart.
    pub margin: u32,
}

impl Layout {
    /// The layout of `plot` whose y tick labels are `y_labels`.
    pub(crate) fn of(plot: &Plot, y_labels: &[String]) -> Self {
        let margin = 12;
        let legend: Vec<String> = plot.series.iter().map(|s| s.name.clone()).collect();
        let line = 28; // the legend's line sample and the gaps beside it
        let widest = legend.iter().map(|n| text_width(n, LABEL_SIZE)).max();
        let column = widest.map_or(0, |w| (w + line + 2 * margin).min(MAX_LEGEND));
        let room = column.saturating_sub(line + 2 * margin);
        let legend = legend.iter().map(|n| cut(n, LABEL_SIZE, room)).collect();
        let legend_left = SIZE.0 - column;
        let chart_width = legend_left - 2 * margin;
        let mut title_size = TITLE_SIZE;
        let plain = plot.title.replace('`', "");
        while title_size > MIN_TITLE_SIZE && text_width(&plain, title_size) > chart_width {
            title_size -= 1;
        }
        // Backticks mark names in markdown; a plot shows the names.
        let title = cut(&plain, title_size, chart_width);
        let widest_y = y_labels.iter().map(|l| text_width(l, LABEL_SIZE)).max();
        let y_label_area = widest_y.unwrap_or(0) + DESC_SIZE + 24;
        Self {
            title_size,
            title,
            legend_left,
            legend,
            y_label_area,
            x_label_area: LABEL_SIZE + DESC_SIZE + 20,
            margin,
        }
    }

    /// The data's rectangle `(left, top, right, bottom)`.
    pub(crate) fn data(&self) -> (u32, u32, u32, u32) {
        let top = self.margin + self.title_size + 12;
        let left = self.margin + self.y_label_area;
        let right = self.legend_left - self.margin;
        let bottom = SIZE.1 - self.margin - self.x_label_area;
        (left, top, right, bottom)
    }
}

/// Series as points `(x, y)`, `log10` of the values with `log` (non-positive values left
/// out); x is the series' own where it has one, else the index.
type Points = Vec<(String, Vec<(f64, f64)>)>;

fn points(p: &Plot) -> Points {
    let at = |s: &Series, i: usize| s.x.as_ref().map_or(i as f64, |x| x[i]);
    p.series
        .iter()
        .map(|s| {
            let kept =
                s.values.iter().enumerate().filter(|(i, y)| {
                    y.is_finite() && (!p.log || **y > 0.0) && at(s, *i).is_finite()
                });
            let pts = kept.map(|(i, y)| (at(s, i), if p.log { y.log10() } else { *y }));
            (s.name.clone(), pts.collect())
        })
        .collect()
}

/// A tick label: whole numbers as such, others with up to three significant decimals
/// (trailing zeros dropped), very small or large ones in scientific notation; on a log axis
/// the value `10^v`.
pub(crate) fn tick(v: f64, log: bool) -> String {
    if log {
        let p = v.round();
        return if (v - p).abs() < 1e-9 {
            format!("1e{p}")
        } else {
            format!("{:.1e}", 10f64.powf(v))
        };
    }
    if v == 0.0 || (v - v.round()).abs() < 1e-9 * v.abs().max(1.0) && v.abs() < 1e6 {
        return format!("{}", v.round() as i64);
    }
    if !(1e-3..1e5).contains(&v.abs()) {
        return format!("{v:.2e}");
    }
    let s = format!("{v:.3}");
    s.trim_end_matches('0').trim_end_matches('.').to_owned()
}

/// A line plot of named series, written to `stem.svg` and `stem.png` (each atomically:
/// drawn to a temporary file, then renamed); with `log`, of the series' base-10 logarithms.
/// Nothing is written when no series has a point; returns whether the files were written.
pub fn plot(stem: &Path, p: &Plot) -> Result<bool> {
    let points = points(p);
    if points.iter().all(|(_, p)| p.is_empty()) {
        return Ok(false);
    }
    register();
    let (svg, svg_tmp) = (stem.with_extension("svg"), stem.with_extension("svg.tmp"));
    draw(
        SVGBackend::new(&svg_tmp, SIZE).into_drawing_area(),
        p,
        &points,
    )?;
    let (png, png_tmp) = (stem.with_extension("png"), stem.with_extension("tmp.png"));
    draw(
        BitMapBackend::new(&png_tmp, SIZE).into_drawing_area(),
        p,
        &points,
    )?;
    for (tmp, path) in [(svg_tmp, svg), (png_tmp, png)] {
        std::fs::rename(&tmp, &path).map_err(|source| RenderError::Io { path, source })?;
    }
    Ok(true)
}

/// The axes' ranges: x over the points, y over the points padded by 5 % (a categorical y
/// axis over its categories).
fn ranges(p: &Plot, series: &Points) -> ((f64, f64), (f64, f64)) {
    let all = || series.iter().flat_map(|(_, p)| p.iter());
    let span = |v: &mut dyn Iterator<Item = f64>| {
        v.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), x| {
            (a.min(x), b.max(x))
        })
    };
    let (x0, x1) = span(&mut all().map(|q| q.0));
    let x = if x1 > x0 { (x0, x1) } else { (x0, x0 + 1.0) };
    if let Some(c) = &p.categories {
        return (x, (-0.5, c.len() as f64 - 0.5));
    }
    let (lo, hi) = span(&mut all().map(|q| q.1));
    let pad = 0.05 * (hi - lo).max(1e-30 * hi.abs().max(1.0));
    (x, (lo - pad, hi + pad))
}

/// The y tick labels the chart will show (for the layout's room): the categories, or the
/// formatted ends and middle of the range.
fn y_labels(p: &Plot, (lo, hi): (f64, f64)) -> Vec<String> {
    match &p.categories {
        Some(c) => c.iter().map(|n| cut(n, LABEL_SIZE, MAX_Y_LABEL)).collect(),
        None => [lo, 0.5 * (lo + hi), hi].map(|v| tick(v, p.log)).to_vec(),
    }
}

fn draw<DB: DrawingBackend>(root: DrawingArea<DB, Shift>, p: &Plot, series: &Points) -> Result<()>
where
    DB::ErrorType: 'static,
{
    let err = |e: DrawingAreaErrorKind<DB::ErrorType>| RenderError::Plot {
        title: p.title.clone(),
        reason: e.to_string(),
    };
    let ((x0, x1), (y0, y1)) = ranges(p, series);
    let layout = Layout::of(p, &y_labels(p, (y0, y1)));
    root.fill(&WHITE).map_err(err)?;
    let (left, legend) = root.split_horizontally(layout.legend_left);
    let mut chart = ChartBuilder::on(&left)
        .caption(&layout.title, ("sans-serif", layout.title_size))
        .margin(layout.margin)
        .x_label_area_size(layout.x_label_area)
        .y_label_area_size(layout.y_label_area)
        .build_cartesian_2d(x0..x1, y0..y1)
        .map_err(err)?;
    let index_axis = p.series.iter().all(|s| s.x.is_none());
    let steps = (x1 - x0).round() as usize + 1;
    let x_format = |v: &f64| tick(*v, false);
    let categories = p.categories.clone().unwrap_or_default();
    let y_format = |v: &f64| match &p.categories {
        Some(_) if (v - v.round()).abs() > 1e-6 => String::new(),
        Some(_) => categories
            .get(v.round() as usize)
            .map_or(String::new(), |n| cut(n, LABEL_SIZE, MAX_Y_LABEL)),
        None => tick(*v, p.log),
    };
    let mut mesh = chart.configure_mesh();
    mesh.x_desc(p.x_label)
        .y_desc(y_desc(p))
        .x_label_formatter(&x_format)
        .y_label_formatter(&y_format)
        .label_style(("sans-serif", LABEL_SIZE))
        .axis_desc_style(("sans-serif", DESC_SIZE));
    if index_axis {
        // At most one label per index: the ticks then fall on whole numbers.
        mesh.x_labels(steps.clamp(2, 10));
    }
    if !categories.is_empty() {
        mesh.y_labels(categories.len().max(2));
    }
    mesh.draw().map_err(err)?;
    for &x in &p.x_marks {
        let mark = BLACK.mix(0.35).stroke_width(1);
        let line = DashedLineSeries::new([(x, y0), (x, y1)], 4, 4, mark);
        chart.draw_series(line).map_err(err)?;
    }
    for (k, (_, points)) in series.iter().enumerate() {
        let style = color(k).stroke_width(2);
        if p.marks == Marks::Points {
            let dots = points.iter().map(|&q| Circle::new(q, 3, style.filled()));
            chart.draw_series(dots).map_err(err)?;
        } else if k >= 6 {
            let line = DashedLineSeries::new(points.iter().copied(), 8, 5, style);
            chart.draw_series(line).map_err(err)?;
        } else {
            let line = LineSeries::new(points.iter().copied(), style);
            chart.draw_series(line).map_err(err)?;
        }
    }
    draw_legend(&legend, &layout, p.marks == Marks::Points).map_err(err)?;
    root.present().map_err(err)?;
    Ok(())
}

fn y_desc(p: &Plot) -> String {
    if p.log {
        format!("{} (log scale)", p.y_label)
    } else {
        p.y_label.to_owned()
    }
}

fn color(k: usize) -> RGBColor {
    let c = COLORS[k % COLORS.len()];
    RGBColor((c >> 16) as u8, (c >> 8) as u8, c as u8)
}

/// The legend in its own column: a line (or dot) sample and the name of each series.
fn draw_legend<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    layout: &Layout,
    dots: bool,
) -> std::result::Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    let top = layout.data().1 as i32;
    let font = ("sans-serif", LABEL_SIZE).into_font();
    for (k, name) in layout.legend.iter().enumerate() {
        let y = top + 8 + k as i32 * (LABEL_SIZE as i32 + 9);
        let style = color(k).stroke_width(2);
        if dots {
            area.draw(&Circle::new((16, y), 3, style.filled()))?;
        } else if k >= 6 {
            let path = plotters::element::DashedPathElement::new([(4, y), (28, y)], 8, 5, style);
            area.draw(&path)?;
        } else {
            area.draw(&PathElement::new(vec![(4, y), (28, y)], style))?;
        }
        let text = Text::new(name.clone(), (34, y - LABEL_SIZE as i32 / 2), font.clone());
        area.draw(&text)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn plot(title: &str, names: &[&str]) -> Plot {
        let series = names
            .iter()
            .map(|n| Series::new(*n, vec![1.0, 2.0]))
            .collect();
        Plot::new("p", title, ["step", "m"]).with(series)
    }

    /// The legend stands right of the data (it never covers a line), every entry fits its
    /// column, the title fits above the data, and the y labels fit their room: for one
    /// series and for twelve with long names and a long title.
    #[test]
    fn the_legend_covers_no_data_and_every_label_fits() {
        let long = "held-out RMS position error against the fine model, coarse step 4x, per-element field (ParaView: coarse_4x_dt_field.vtu)";
        let names: Vec<String> = (0..12)
            .map(|k| {
                format!("Eisenstat-Walker pcg(StaleCholesky {{ max_age: {k} }}) with a long tail")
            })
            .collect();
        let names: Vec<&str> = names.iter().map(String::as_str).collect();
        for p in [plot("loss", &["loss"]), plot(long, &names)] {
            let labels = y_labels(&p, (-1.2345e-3, 6.789e4));
            let l = Layout::of(&p, &labels);
            let (left, top, right, bottom) = l.data();
            assert!(left < right && top < bottom, "{l:?}");
            assert!(right < l.legend_left, "the legend starts after the data");
            for entry in &l.legend {
                let end = l.legend_left + 34 + text_width(entry, LABEL_SIZE);
                assert!(end <= SIZE.0, "legend entry {entry:?} runs off the canvas");
            }
            let title = text_width(&l.title, l.title_size);
            assert!(title <= l.legend_left - 2 * l.margin, "title {title} px");
            for label in &labels {
                let w = text_width(label, LABEL_SIZE);
                assert!(w + DESC_SIZE + 10 <= l.y_label_area, "y label {label:?}");
            }
            let rows = l.legend.len() as u32 * (LABEL_SIZE + 9);
            assert!(top + rows <= SIZE.1, "the legend's rows fit the height");
        }
    }

    #[test]
    fn ticks_have_no_stray_digits() {
        assert_eq!(tick(0.09, false), "0.09");
        assert_eq!(tick(3.0, false), "3");
        assert_eq!(tick(0.0, false), "0");
        assert_eq!(tick(1.25e-5, false), "1.25e-5");
        assert_eq!(tick(123456.0, false), "123456");
        assert_eq!(tick(1234567.5, false), "1.23e6");
        assert_eq!(tick(-3.0, true), "1e-3");
        assert_eq!(tick(0.15, false), "0.15");
    }
}
