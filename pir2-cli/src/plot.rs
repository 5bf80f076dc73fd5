//! PNG plots (plotters with an embedded DejaVu font: no system fonts needed): study series
//! and run traces. A leaf: it knows nothing of studies (`study::cells` turns a study's cells
//! into [`Series`]).

use std::path::Path;
use std::sync::Once;

use anyhow::{anyhow, Result};
use plotters::prelude::*;
use serde::{Deserialize, Serialize};

use pir2_runtime::RunTrace;

static FONT: Once = Once::new();

fn register_font() {
    FONT.call_once(|| {
        let _ = plotters::style::register_font(
            "sans-serif",
            FontStyle::Normal,
            dejavu::sans::regular(),
        );
    });
}

/// One curve of a study plot: mean ± std of success per x value.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Series {
    /// Legend label.
    pub label: String,
    /// Points `(x, mean, std)`.
    pub points: Vec<(f64, f64, f64)>,
}

const COLORS: [RGBColor; 10] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(127, 127, 127),
    RGBColor(188, 189, 34),
    RGBColor(23, 190, 207),
];

/// Success (mean ± std) against an x axis, one line per series, error bars, legend.
pub fn plot_series(
    path: &Path,
    title: &str,
    x_desc: &str,
    y_desc: &str,
    series: &[Series],
) -> Result<()> {
    register_font();
    let root = BitMapBackend::new(path, (1240, 620)).into_drawing_area();
    draw_series_plot(&root, title, x_desc, y_desc, series)
        .map_err(|e| anyhow!("plot {}: {e}", path.display()))?;
    root.present()
        .map_err(|e| anyhow!("writing {}: {e}", path.display()))?;
    Ok(())
}

/// Draws [`plot_series`]'s figure on `root` (whole image: title, chart, legend panel).
fn draw_series_plot(
    root: &DrawingArea<BitMapBackend<'_>, plotters::coord::Shift>,
    title: &str,
    x_desc: &str,
    y_desc: &str,
    series: &[Series],
) -> Result<()> {
    root.fill(&WHITE).map_err(|e| anyhow!("{e}"))?;
    // The title spans the whole image at 24 px, scaled down (text width is proportional to
    // the size; 10 px at least) when that is wider than the image less a 16 px margin per
    // side, so a long title is never cut at the edges.
    let (width, _) = root.dim_in_pixel();
    let (w24, _) = root
        .estimate_text_size(title, &("sans-serif", 24.0).into_text_style(root))
        .map_err(|e| anyhow!("{e}"))?;
    let fit = f64::from(width.saturating_sub(32)) / f64::from(w24.max(1));
    let title_size = (24.0 * fit).floor().clamp(10.0, 24.0);
    let root = root
        .titled(title, ("sans-serif", title_size))
        .map_err(|e| anyhow!("{e}"))?;
    // The legend gets its own panel on the right so it never hides a data point.
    let (plot_area, legend_area) = root.split_horizontally(900);
    let (mut xmin, mut xmax) = (f64::MAX, f64::MIN);
    for s in series {
        for p in &s.points {
            xmin = xmin.min(p.0);
            xmax = xmax.max(p.0);
        }
    }
    if xmin > xmax {
        return Err(anyhow!("nothing to plot"));
    }
    let pad = ((xmax - xmin) * 0.08).max(0.3);
    // Integer x values (delays, horizons) get integer ticks.
    let integer_x = series
        .iter()
        .flat_map(|s| &s.points)
        .all(|p| p.0.fract() == 0.0);
    let mut chart = ChartBuilder::on(&plot_area)
        .margin(16)
        .x_label_area_size(44)
        .y_label_area_size(56)
        .build_cartesian_2d((xmin - pad)..(xmax + pad), 0f64..1.05f64)
        .map_err(|e| anyhow!("{e}"))?;
    let mut mesh = chart.configure_mesh();
    if integer_x && xmax - xmin <= 20.0 {
        mesh.x_labels((xmax - xmin) as usize + 1)
            .x_label_formatter(&|x| format!("{x:.0}"));
    }
    mesh.x_desc(x_desc)
        .y_desc(y_desc)
        .axis_desc_style(("sans-serif", 18))
        .label_style(("sans-serif", 15))
        .draw()
        .map_err(|e| anyhow!("{e}"))?;
    let n = series.len().max(1) as f64;
    for (i, s) in series.iter().enumerate() {
        let c = COLORS[i % COLORS.len()];
        // Small horizontal offsets so error bars of different series do not overlap.
        let off = (i as f64 - (n - 1.0) / 2.0) * 0.04;
        let pts: Vec<(f64, f64)> = s.points.iter().map(|p| (p.0 + off, p.1)).collect();
        chart
            .draw_series(LineSeries::new(pts.clone(), c.stroke_width(2)))
            .map_err(|e| anyhow!("{e}"))?;
        chart
            .draw_series(pts.iter().map(|&p| Circle::new(p, 4, c.filled())))
            .map_err(|e| anyhow!("{e}"))?;
        chart
            .draw_series(s.points.iter().map(|p| {
                ErrorBar::new_vertical(
                    p.0 + off,
                    (p.1 - p.2).max(0.0),
                    p.1,
                    (p.1 + p.2).min(1.05),
                    c.stroke_width(1),
                    8,
                )
            }))
            .map_err(|e| anyhow!("{e}"))?;
    }
    let font = ("sans-serif", 15).into_font();
    for (i, s) in series.iter().enumerate() {
        let c = COLORS[i % COLORS.len()];
        let y = 40 + 28 * i as i32;
        legend_area
            .draw(&PathElement::new(vec![(8, y), (36, y)], c.stroke_width(3)))
            .map_err(|e| anyhow!("{e}"))?;
        legend_area
            .draw(&Circle::new((22, y), 4, c.filled()))
            .map_err(|e| anyhow!("{e}"))?;
        legend_area
            .draw(&Text::new(s.label.clone(), (44, y - 8), font.clone()))
            .map_err(|e| anyhow!("{e}"))?;
    }
    Ok(())
}

/// A run trace: call latency (ms) and `d`, `d_vis` per call.
pub fn plot_trace(path: &Path, trace: &RunTrace) -> Result<()> {
    register_font();
    let root = BitMapBackend::new(path, (960, 640)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| anyhow!("{e}"))?;
    let (top, bottom) = root.split_vertically(320);
    let n = trace.calls.len().max(1) as f64;
    let lat: Vec<(f64, f64)> = trace
        .calls
        .iter()
        .enumerate()
        .map(|(i, c)| (i as f64, c.latency as f64 / 1e6))
        .collect();
    let lmax = lat.iter().map(|p| p.1).fold(1e-3, f64::max) * 1.1;
    let mut c1 = ChartBuilder::on(&top)
        .caption("call latency", ("sans-serif", 20))
        .margin(10)
        .x_label_area_size(36)
        .y_label_area_size(56)
        .build_cartesian_2d(0f64..n, 0f64..lmax)
        .map_err(|e| anyhow!("{e}"))?;
    c1.configure_mesh()
        .x_desc("call")
        .y_desc("ms")
        .draw()
        .map_err(|e| anyhow!("{e}"))?;
    c1.draw_series(LineSeries::new(lat, COLORS[0]))
        .map_err(|e| anyhow!("{e}"))?;
    let dmax = trace
        .calls
        .iter()
        .map(|c| c.d.max(c.d_vis).max(c.elapsed))
        .max()
        .unwrap_or(1) as f64
        + 1.0;
    let mut c2 = ChartBuilder::on(&bottom)
        .caption("d, d_vis, elapsed ticks", ("sans-serif", 20))
        .margin(10)
        .x_label_area_size(36)
        .y_label_area_size(56)
        .build_cartesian_2d(0f64..n, 0f64..dmax)
        .map_err(|e| anyhow!("{e}"))?;
    c2.configure_mesh()
        .x_desc("call")
        .y_desc("ticks")
        .draw()
        .map_err(|e| anyhow!("{e}"))?;
    for (k, (label, f)) in [
        (
            "d",
            (|c: &pir2_runtime::CallRecord| c.d as f64) as fn(&pir2_runtime::CallRecord) -> f64,
        ),
        ("d_vis", |c| c.d_vis as f64),
        ("elapsed", |c| c.elapsed as f64),
    ]
    .into_iter()
    .enumerate()
    {
        let col = COLORS[k + 1];
        c2.draw_series(LineSeries::new(
            trace
                .calls
                .iter()
                .enumerate()
                .map(|(i, c)| (i as f64, f(c))),
            col,
        ))
        .map_err(|e| anyhow!("{e}"))?
        .label(label)
        .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], col));
    }
    c2.configure_series_labels()
        .border_style(BLACK)
        .background_style(WHITE)
        .draw()
        .map_err(|e| anyhow!("{e}"))?;
    root.present()
        .map_err(|e| anyhow!("writing {}: {e}", path.display()))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Renders the series plot into memory; returns the RGB buffer and the image width.
    fn render(title: &str) -> (Vec<u8>, usize) {
        register_font();
        let (w, h) = (1240usize, 620usize);
        let mut buf = vec![0u8; w * h * 3];
        {
            let root =
                BitMapBackend::with_buffer(&mut buf, (w as u32, h as u32)).into_drawing_area();
            let series = vec![Series {
                label: "a".into(),
                points: vec![(1.0, 0.5, 0.1), (2.0, 0.4, 0.05)],
            }];
            draw_series_plot(&root, title, "x", "y", &series).unwrap();
            root.present().unwrap();
        }
        (buf, w)
    }

    /// Dark pixels in the title band (the top 30 rows) within `cols` of the image.
    fn title_ink(buf: &[u8], w: usize, cols: std::ops::Range<usize>) -> usize {
        (0..30)
            .flat_map(|y| cols.clone().map(move |x| (y * w + x) * 3))
            .filter(|&i| buf[i] < 128 && buf[i + 1] < 128 && buf[i + 2] < 128)
            .count()
    }

    #[test]
    fn a_long_title_fits_the_image() {
        let long = "Leap cube (deployment study): success (mean ± std over 3 seeds) \
                    (best checkpoint per cell), with some more words to be sure";
        let (buf, w) = render(long);
        assert!(title_ink(&buf, w, 0..w) > 200, "the title is drawn");
        assert_eq!(
            title_ink(&buf, w, 0..8),
            0,
            "the title reaches the left edge"
        );
        assert_eq!(
            title_ink(&buf, w, w - 8..w),
            0,
            "the title reaches the right edge"
        );
        let (short, _) = render("short");
        assert!(title_ink(&short, w, 0..w) > 50);
    }
}
