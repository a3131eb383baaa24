//! Robustness-curve figures (`figures/curve_<benchmark>.svg`): per method, the
//! benchmark's number against the severity rung with its 95% interval, the
//! paper's number marked at rung 0 (a black bar across the method's point), the
//! legend beside the plot so it covers no data.

use std::path::Path;

use anyhow::{anyhow, Result};
use plotters::prelude::*;

use super::curves::CurvePoint;
use super::plots::{unique, PALETTE};
use super::results::ExperimentResults;

fn err<E: std::fmt::Display>(e: E) -> anyhow::Error {
    anyhow!("drawing a curve figure: {e}")
}

/// A curve figure: (benchmark, metric, title, y axis, y range top or 0 for the data's).
pub type CurveFigure = (&'static str, &'static str, &'static str, &'static str, f64);

/// The curves drawn.
pub const CURVE_FIGURES: [CurveFigure; 3] = [
    (
        "ttf",
        "ttf",
        "Time to Fall against severity (mean over table I's cells)",
        "time to fall",
        1.05,
    ),
    (
        "platform",
        "success_pct",
        "Walking off a platform against severity",
        "success %",
        105.0,
    ),
    (
        "race",
        "return_q25",
        "Race-track return (0.25 quantile) against severity",
        "return q0.25",
        0.0,
    ),
];

/// One figure; nothing is written when the benchmark has no points.
pub(super) fn curve_figure(
    r: &ExperimentResults,
    &(benchmark, metric, title, y_desc, y_top): &CurveFigure,
    path: &Path,
) -> Result<()> {
    let points: Vec<&CurvePoint> = r.curves.iter().filter(|p| p.metric == metric).collect();
    if points.is_empty() {
        return Ok(());
    }
    let methods = unique(points.iter().map(|p| p.policy.clone()));
    let rung_max = points.iter().map(|p| p.severity).max().unwrap_or(0) as f64;
    let (lo, hi) = points.iter().fold((0.0f64, f64::MIN), |(lo, hi), p| {
        let seeds = p.seeds.iter().copied();
        (
            seeds.clone().fold(lo.min(p.estimate.lo), f64::min),
            seeds.fold(hi.max(p.estimate.hi), f64::max),
        )
    });
    let y = if y_top > 0.0 {
        0.0..y_top
    } else {
        lo.min(0.0)..(hi.max(1e-6) * 1.1)
    };
    let root = SVGBackend::new(path, (900, 460)).into_drawing_area();
    root.fill(&WHITE).map_err(err)?;
    let (plot, legend) = root.split_horizontally(640);
    let mut chart = ChartBuilder::on(&plot)
        .caption(title, ("sans-serif", 17))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(55)
        .build_cartesian_2d(-0.3..rung_max + 0.3, y)
        .map_err(err)?;
    chart
        .configure_mesh()
        .disable_x_mesh()
        .light_line_style(WHITE)
        .bold_line_style(BLACK.mix(0.12))
        .x_labels(rung_max as usize + 1)
        .x_label_formatter(&|x| format!("rung {x:.0}"))
        .x_desc("severity (rung 0 = the paper's protocol)")
        .y_desc(y_desc)
        .draw()
        .map_err(err)?;
    let n = methods.len().max(1) as f64;
    for (i, m) in methods.iter().enumerate() {
        let color = PALETTE[i % PALETTE.len()];
        let dx = (i as f64 - (n - 1.0) / 2.0) * 0.04; // side by side, whiskers apart
        let mut mine: Vec<&&CurvePoint> = points.iter().filter(|p| p.policy == *m).collect();
        mine.sort_by_key(|p| p.severity);
        let xy = |p: &CurvePoint| (p.severity as f64 + dx, p.estimate.value);
        chart
            .draw_series(LineSeries::new(
                mine.iter().map(|p| xy(p)),
                color.stroke_width(2),
            ))
            .map_err(err)?;
        chart
            .draw_series(mine.iter().map(|p| Circle::new(xy(p), 4, color.filled())))
            .map_err(err)?;
        chart
            .draw_series(mine.iter().map(|p| {
                let x = p.severity as f64 + dx;
                PathElement::new(vec![(x, p.estimate.lo), (x, p.estimate.hi)], color)
            }))
            .map_err(err)?;
        // each training seed's own number: a ring beside the method's point
        chart
            .draw_series(mine.iter().flat_map(|p| {
                let x = p.severity as f64 + dx;
                p.seeds.iter().map(move |&v| Circle::new((x, v), 3, color))
            }))
            .map_err(err)?;
        let paper = r
            .curve_paper
            .iter()
            .find(|(b, mm, _)| b == benchmark && mm == m);
        if let Some((_, _, v)) = paper {
            // the method's colour, a black core: whose number it is, and that it is the paper's
            let tick = vec![(dx - 0.12, *v), (dx + 0.12, *v)];
            chart
                .draw_series([
                    PathElement::new(tick.clone(), color.stroke_width(6)),
                    PathElement::new(tick, BLACK.stroke_width(2)),
                ])
                .map_err(err)?;
        }
    }
    draw_legend(
        &legend,
        &methods,
        r.curve_paper.iter().any(|(b, _, _)| b == benchmark),
        points.iter().any(|p| !p.seeds.is_empty()),
    )?;
    root.present().map_err(err)
}

/// The legend in its own area right of the plot.
fn draw_legend<DB: DrawingBackend>(
    area: &DrawingArea<DB, plotters::coord::Shift>,
    methods: &[String],
    with_paper: bool,
    with_seeds: bool,
) -> Result<()>
where
    DB::ErrorType: 'static,
{
    let style = ("sans-serif", 14).into_font().color(&BLACK);
    for (i, m) in methods.iter().enumerate() {
        let y = 60 + 24 * i as i32;
        let color = PALETTE[i % PALETTE.len()];
        area.draw(&PathElement::new(
            vec![(10, y), (40, y)],
            color.stroke_width(2),
        ))
        .map_err(err)?;
        area.draw(&Circle::new((25, y), 4, color.filled()))
            .map_err(err)?;
        area.draw(&Text::new(m.clone(), (48, y - 8), style.clone()))
            .map_err(err)?;
    }
    let y = 60 + 24 * methods.len() as i32 + 12;
    if with_paper {
        area.draw(&PathElement::new(
            vec![(14, y), (36, y)],
            BLACK.mix(0.35).stroke_width(6),
        ))
        .map_err(err)?;
        area.draw(&PathElement::new(
            vec![(14, y), (36, y)],
            BLACK.stroke_width(2),
        ))
        .map_err(err)?;
        for (k, line) in ["the paper's number at rung 0", "(in the method's colour)"]
            .iter()
            .enumerate()
        {
            area.draw(&Text::new(
                *line,
                (48, y - 8 + 18 * k as i32),
                style.clone(),
            ))
            .map_err(err)?;
        }
    }
    let note = ("sans-serif", 12).into_font().color(&BLACK.mix(0.7));
    area.draw(&Text::new(
        "whiskers: 95% bootstrap over robots",
        (10, y + 42),
        note.clone(),
    ))
    .map_err(err)?;
    if with_seeds {
        area.draw(&Text::new(
            "rings: each training seed's own number",
            (10, y + 60),
            note,
        ))
        .map_err(err)?;
    }
    Ok(())
}
