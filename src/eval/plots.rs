//! PNG figures of an evaluation: the PR curve and the similarity matrix.
use super::metrics::PrPoint;
use anyhow::{anyhow, Result};
use plotters::prelude::*;
use std::path::Path;

fn err<E: std::fmt::Display>(e: E) -> anyhow::Error {
    anyhow!("plotting: {e}")
}

/// The area a figure is drawn on.
pub type Canvas<'a> = DrawingArea<BitMapBackend<'a>, plotters::coord::Shift>;

/// A `size` RGB picture drawn by `draw` into memory, then written to `path` as PNG (by the
/// `image` crate the rest of loopd decodes with). Every figure of loopd's (and the benches') is
/// made here.
pub fn png(path: &Path, size: (u32, u32), draw: impl FnOnce(&Canvas<'_>) -> Result<()>) -> Result<()> {
    let mut pixels = vec![0u8; size.0 as usize * size.1 as usize * 3];
    {
        let root = BitMapBackend::with_buffer(&mut pixels, size).into_drawing_area();
        draw(&root)?;
        root.present().map_err(err)?;
    }
    image::save_buffer_with_format(path, &pixels, size.0, size.1, image::ColorType::Rgb8, image::ImageFormat::Png)
        .map_err(|e| anyhow!("writing {}: {e}", path.display()))
}

/// Precision against recall, one point per threshold, with R@100P marked in the title.
pub fn pr_curve(path: &Path, curves: &[(String, Vec<PrPoint>)], title: &str) -> Result<()> {
    let series: Vec<(String, Vec<(f64, f64)>)> = curves
        .iter()
        .map(|(name, pts)| {
            let mut line = vec![(0.0, 1.0)];
            line.extend(pts.iter().map(|p| (p.recall, p.precision)));
            (name.clone(), line)
        })
        .collect();
    let axes = Axes { size: (800, 600), x: 0.0..1.0, y: 0.0..1.02, desc: ("recall", "precision"), y_label: 55 };
    line_chart(path, title, axes, &series, Extras::default())
}

/// The frame of a line chart.
struct Axes<'a> {
    size: (u32, u32),
    x: std::ops::Range<f64>,
    y: std::ops::Range<f64>,
    desc: (&'a str, &'a str),
    y_label: u32,
}

/// What one chart adds to its lines.
#[derive(Default)]
struct Extras {
    /// The y = x line, drawn under the series.
    diagonal: bool,
    /// A dot on every point.
    markers: bool,
    /// The legend in the upper left corner (else the upper right).
    legend_left: bool,
}

/// Named series of (x, y) points as lines with a legend: every chart of this module but the
/// similarity matrix.
fn line_chart(
    path: &Path,
    title: &str,
    axes: Axes,
    series: &[(String, Vec<(f64, f64)>)],
    extras: Extras,
) -> Result<()> {
    png(path, axes.size, |root| line_chart_on(root, title, axes, series, extras))
}

fn line_chart_on(
    root: &Canvas<'_>,
    title: &str,
    axes: Axes,
    series: &[(String, Vec<(f64, f64)>)],
    extras: Extras,
) -> Result<()> {
    root.fill(&WHITE).map_err(err)?;
    let mut chart = ChartBuilder::on(root)
        .caption(title, ("sans-serif", 22))
        .margin(15)
        .x_label_area_size(45)
        .y_label_area_size(axes.y_label)
        .build_cartesian_2d(axes.x, axes.y)
        .map_err(err)?;
    chart.configure_mesh().x_desc(axes.desc.0).y_desc(axes.desc.1).draw().map_err(err)?;
    if extras.diagonal {
        chart.draw_series(LineSeries::new(vec![(0.0, 0.0), (1.0, 1.0)], BLACK.mix(0.4))).map_err(err)?;
    }
    for (i, (name, pts)) in series.iter().enumerate() {
        let color = Palette99::pick(i).to_rgba();
        chart
            .draw_series(LineSeries::new(pts.clone(), color.stroke_width(2)))
            .map_err(err)?
            .label(name.clone())
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2)));
        if extras.markers {
            chart.draw_series(pts.iter().map(|&p| Circle::new(p, 4, color.filled()))).map_err(err)?;
        }
    }
    let mut labels = chart.configure_series_labels();
    if extras.legend_left {
        labels.position(SeriesLabelPosition::UpperLeft);
    }
    labels.background_style(WHITE.mix(0.8)).border_style(BLACK).draw().map_err(err)?;
    Ok(())
}

/// Query x reference cosine similarities (rows: queries), max-pooled down to at most 800 pixels
/// a side; brighter is more similar. Ground-truth loops are drawn as green dots when given.
pub fn similarity(path: &Path, scores: &[f32], rows: usize, cols: usize, truth: &[(usize, usize)]) -> Result<()> {
    let (w, h) = (cols.clamp(1, 800), rows.clamp(1, 800));
    png(path, (w as u32, h as u32), |root| similarity_on(root, (w, h), scores, (rows, cols), truth))
}

fn similarity_on(
    root: &Canvas<'_>,
    (w, h): (usize, usize),
    scores: &[f32],
    (rows, cols): (usize, usize),
    truth: &[(usize, usize)],
) -> Result<()> {
    root.fill(&BLACK).map_err(err)?;
    let (lo, hi) = scores.iter().fold((f32::MAX, f32::MIN), |(a, b), &s| (a.min(s), b.max(s)));
    let span = (hi - lo).max(1e-6);
    let mut pooled = vec![f32::MIN; w * h];
    for r in 0..rows {
        for c in 0..cols {
            let cell = &mut pooled[(r * h / rows) * w + c * w / cols];
            *cell = cell.max(scores[r * cols + c]);
        }
    }
    for (i, &v) in pooled.iter().enumerate() {
        let t = ((v - lo) / span).clamp(0.0, 1.0);
        // black -> red -> yellow -> white
        let (r, g, b) = ((3.0 * t).min(1.0), (3.0 * t - 1.0).clamp(0.0, 1.0), (3.0 * t - 2.0).clamp(0.0, 1.0));
        let color = RGBColor((r * 255.0) as u8, (g * 255.0) as u8, (b * 255.0) as u8);
        root.draw_pixel(((i % w) as i32, (i / w) as i32), &color).map_err(err)?;
    }
    for &(q, r) in truth {
        if q < rows && r < cols {
            root.draw_pixel(((r * w / cols) as i32, (q * h / rows) as i32), &GREEN).map_err(err)?;
        }
    }
    Ok(())
}

/// Named series of (x, y) points as lines (training curves).
pub fn lines(path: &Path, title: &str, axes: (&str, &str), series: &[(String, Vec<(f64, f64)>)]) -> Result<()> {
    let pts = series.iter().flat_map(|(_, p)| p.iter());
    let (x1, y0, y1) =
        pts.fold((1f64, f64::INFINITY, f64::NEG_INFINITY), |(x1, y0, y1), &(x, y)| (x1.max(x), y0.min(y), y1.max(y)));
    let (y0, y1) = if y0.is_finite() { (y0.min(0.0), y1.max(y0 + 1e-3) * 1.05) } else { (0.0, 1.0) };
    let axes = Axes { size: (800, 500), x: 0.0..x1, y: y0..y1, desc: axes, y_label: 60 };
    line_chart(path, title, axes, series, Extras::default())
}

/// Reliability diagrams, one series per set: each bin's mean confidence against the share of its
/// candidates that were true loops (the diagonal is perfect calibration); the bins' counts in
/// the legend's name are the caller's.
pub fn reliability(path: &Path, title: &str, series: &[(String, Vec<super::metrics::ReliabilityBin>)]) -> Result<()> {
    let series: Vec<(String, Vec<(f64, f64)>)> = series
        .iter()
        .map(|(name, bins)| {
            (name.clone(), bins.iter().filter(|b| b.count > 0).map(|b| (b.mean_confidence, b.frequency)).collect())
        })
        .collect();
    let axes = Axes {
        size: (800, 640),
        x: 0.0..1.0,
        y: 0.0..1.0,
        desc: ("confidence (bin mean)", "share of true loops"),
        y_label: 55,
    };
    line_chart(path, title, axes, &series, Extras { diagonal: true, markers: true, legend_left: true })
}
