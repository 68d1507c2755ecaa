//! PNG figures of an evaluation: the PR curve and the similarity matrix.
use super::metrics::PrPoint;
use anyhow::{anyhow, Result};
use plotters::prelude::*;
use std::path::Path;

fn err<E: std::fmt::Display>(e: E) -> anyhow::Error {
    anyhow!("plotting: {e}")
}

/// Precision against recall, one point per threshold, with R@100P marked in the title.
pub fn pr_curve(path: &Path, curves: &[(String, Vec<PrPoint>)], title: &str) -> Result<()> {
    let root = BitMapBackend::new(path, (800, 600)).into_drawing_area();
    root.fill(&WHITE).map_err(err)?;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 22))
        .margin(15)
        .x_label_area_size(45)
        .y_label_area_size(55)
        .build_cartesian_2d(0f64..1.0, 0f64..1.02)
        .map_err(err)?;
    chart.configure_mesh().x_desc("recall").y_desc("precision").draw().map_err(err)?;
    for (i, (name, pts)) in curves.iter().enumerate() {
        let color = Palette99::pick(i).to_rgba();
        let mut line: Vec<(f64, f64)> = vec![(0.0, 1.0)];
        line.extend(pts.iter().map(|p| (p.recall, p.precision)));
        chart
            .draw_series(LineSeries::new(line, color.stroke_width(2)))
            .map_err(err)?
            .label(name.clone())
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2)));
    }
    chart.configure_series_labels().background_style(WHITE.mix(0.8)).border_style(BLACK).draw().map_err(err)?;
    root.present().map_err(err)?;
    Ok(())
}

/// Query x reference cosine similarities (rows: queries), max-pooled down to at most 800 pixels
/// a side; brighter is more similar. Ground-truth loops are drawn as green dots when given.
pub fn similarity(path: &Path, scores: &[f32], rows: usize, cols: usize, truth: &[(usize, usize)]) -> Result<()> {
    let (w, h) = (cols.clamp(1, 800), rows.clamp(1, 800));
    let root = BitMapBackend::new(path, (w as u32, h as u32)).into_drawing_area();
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
    root.present().map_err(err)?;
    Ok(())
}

/// Named series of (x, y) points as lines (training curves).
pub fn lines(path: &Path, title: &str, axes: (&str, &str), series: &[(String, Vec<(f64, f64)>)]) -> Result<()> {
    let pts = series.iter().flat_map(|(_, p)| p.iter());
    let (x1, y0, y1) =
        pts.fold((1f64, f64::INFINITY, f64::NEG_INFINITY), |(x1, y0, y1), &(x, y)| (x1.max(x), y0.min(y), y1.max(y)));
    let (y0, y1) = if y0.is_finite() { (y0.min(0.0), y1.max(y0 + 1e-3) * 1.05) } else { (0.0, 1.0) };
    let root = BitMapBackend::new(path, (800, 500)).into_drawing_area();
    root.fill(&WHITE).map_err(err)?;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 22))
        .margin(15)
        .x_label_area_size(45)
        .y_label_area_size(60)
        .build_cartesian_2d(0f64..x1, y0..y1)
        .map_err(err)?;
    chart.configure_mesh().x_desc(axes.0).y_desc(axes.1).draw().map_err(err)?;
    for (i, (name, p)) in series.iter().enumerate() {
        let color = Palette99::pick(i).to_rgba();
        chart
            .draw_series(LineSeries::new(p.clone(), color.stroke_width(2)))
            .map_err(err)?
            .label(name.clone())
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2)));
    }
    chart.configure_series_labels().background_style(WHITE.mix(0.8)).border_style(BLACK).draw().map_err(err)?;
    root.present().map_err(err)?;
    Ok(())
}

/// Reliability diagrams, one series per set: each bin's mean confidence against the share of its
/// candidates that were true loops (the diagonal is perfect calibration); the bins' counts in
/// the legend's name are the caller's.
pub fn reliability(path: &Path, title: &str, series: &[(String, Vec<super::metrics::ReliabilityBin>)]) -> Result<()> {
    let root = BitMapBackend::new(path, (800, 640)).into_drawing_area();
    root.fill(&WHITE).map_err(err)?;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 22))
        .margin(15)
        .x_label_area_size(45)
        .y_label_area_size(55)
        .build_cartesian_2d(0f64..1.0, 0f64..1.0)
        .map_err(err)?;
    chart.configure_mesh().x_desc("confidence (bin mean)").y_desc("share of true loops").draw().map_err(err)?;
    chart.draw_series(LineSeries::new(vec![(0.0, 0.0), (1.0, 1.0)], BLACK.mix(0.4))).map_err(err)?;
    for (i, (name, bins)) in series.iter().enumerate() {
        let color = Palette99::pick(i).to_rgba();
        let pts: Vec<(f64, f64)> =
            bins.iter().filter(|b| b.count > 0).map(|b| (b.mean_confidence, b.frequency)).collect();
        chart
            .draw_series(LineSeries::new(pts.clone(), color.stroke_width(2)))
            .map_err(err)?
            .label(name.clone())
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2)));
        chart.draw_series(pts.into_iter().map(|p| Circle::new(p, 4, color.filled()))).map_err(err)?;
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperLeft)
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()
        .map_err(err)?;
    root.present().map_err(err)?;
    Ok(())
}
