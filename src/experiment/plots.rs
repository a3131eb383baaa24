//! SVG figures of an experiment (plotters): grouped bars with interval whiskers.

use std::path::Path;

use anyhow::{anyhow, Result};
use plotters::prelude::*;

use super::benchmark::FigureEntry;
use super::curve_plots::{CurveFigure, CURVE_FIGURES};
use super::results::ExperimentResults;
use super::stats::Estimate;

pub(super) const PALETTE: [RGBColor; 7] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
];

fn err<E: std::fmt::Display>(e: E) -> anyhow::Error {
    anyhow!("drawing a figure: {e}")
}

/// What one bar panel draws for (group, series): the estimate, each training
/// seed's value, and the paper's number.
struct BarData<'a> {
    value: &'a dyn Fn(usize, usize) -> Option<Estimate>,
    seeds: &'a dyn Fn(usize, usize) -> Vec<f64>,
    paper: &'a dyn Fn(usize, usize) -> Option<f64>,
}

/// Width of the legend column right of the panels (px).
const LEGEND_W: u32 = 210;

/// The legend, in its own column so it covers no bar: a swatch per series, the
/// seed dots, the whiskers and (when drawn) the paper's tick.
fn bar_legend<DB: DrawingBackend>(
    area: &DrawingArea<DB, plotters::coord::Shift>,
    series: &[String],
    with_paper: bool,
) -> Result<()>
where
    DB::ErrorType: 'static,
{
    let style = ("sans-serif", 13).into_font().color(&BLACK);
    let mut y = 50;
    for (i, name) in series.iter().enumerate() {
        let color = PALETTE[i % PALETTE.len()];
        area.draw(&Rectangle::new([(10, y - 6), (24, y + 6)], color.filled()))
            .map_err(err)?;
        area.draw(&Text::new(name.clone(), (32, y - 7), style.clone()))
            .map_err(err)?;
        y += 22;
    }
    y += 8;
    area.draw(&Circle::new((17, y), 3, BLACK.filled()))
        .map_err(err)?;
    area.draw(&Text::new("a training seed", (32, y - 7), style.clone()))
        .map_err(err)?;
    y += 22;
    area.draw(&PathElement::new(vec![(17, y - 7), (17, y + 7)], BLACK))
        .map_err(err)?;
    area.draw(&Text::new("95% interval", (32, y - 7), style.clone()))
        .map_err(err)?;
    if with_paper {
        y += 22;
        area.draw(&PathElement::new(
            vec![(8, y), (26, y)],
            BLACK.stroke_width(3),
        ))
        .map_err(err)?;
        area.draw(&Text::new("the paper's number", (32, y - 7), style))
            .map_err(err)?;
    }
    Ok(())
}

/// One panel of grouped bars: `groups` on x, one bar per series, whiskers at [lo, hi],
/// a dot at each training seed's own value, a black tick at the paper's number.
fn bars<DB: DrawingBackend>(
    area: &DrawingArea<DB, plotters::coord::Shift>,
    (title, y_label): (&str, &str),
    groups: &[String],
    series: &[String],
    data: &BarData,
    y_max: f64,
) -> Result<()>
where
    DB::ErrorType: 'static,
{
    let n = groups.len().max(1) as f64;
    let mut chart = ChartBuilder::on(area)
        .caption(title, ("sans-serif", 18))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(50)
        .build_cartesian_2d(0.0..n, 0.0..y_max)
        .map_err(err)?;
    let names = groups.to_vec();
    chart
        .configure_mesh()
        .disable_x_mesh()
        .light_line_style(WHITE)
        .bold_line_style(BLACK.mix(0.12))
        .x_labels(groups.len() * 2 + 1)
        .x_label_formatter(&move |x| {
            let k = x.floor() as usize;
            if (x - k as f64 - 0.5).abs() < 0.26 {
                names.get(k).cloned().unwrap_or_default()
            } else {
                String::new()
            }
        })
        .y_desc(y_label)
        .draw()
        .map_err(err)?;
    let m = series.len().max(1) as f64;
    let width = 0.8 / m;
    for si in 0..series.len() {
        let color = PALETTE[si % PALETTE.len()];
        let mut rects = Vec::new();
        let mut whiskers = Vec::new();
        let mut dots = Vec::new();
        let mut ticks = Vec::new();
        for gi in 0..groups.len() {
            if let Some(e) = (data.value)(gi, si) {
                let x0 = gi as f64 + 0.1 + si as f64 * width;
                rects.push(Rectangle::new(
                    [(x0, 0.0), (x0 + width * 0.9, e.value)],
                    color.filled(),
                ));
                let xc = x0 + width * 0.45;
                whiskers.push(PathElement::new(
                    vec![(xc, e.lo), (xc, e.hi)],
                    BLACK.stroke_width(1),
                ));
                if let Some(p) = (data.paper)(gi, si) {
                    ticks.push(PathElement::new(
                        vec![(x0 - width * 0.05, p), (x0 + width * 0.95, p)],
                        BLACK.stroke_width(3),
                    ));
                }
                let per_seed = (data.seeds)(gi, si);
                if per_seed.len() > 1 {
                    for (k, v) in per_seed.iter().enumerate() {
                        let dx = width * 0.9 * (k as f64 + 1.0) / (per_seed.len() as f64 + 1.0);
                        dots.push(Circle::new((x0 + dx, *v), 3, BLACK.filled()));
                    }
                }
            }
        }
        chart.draw_series(rects).map_err(err)?;
        chart.draw_series(whiskers).map_err(err)?;
        chart.draw_series(dots).map_err(err)?;
        chart.draw_series(ticks).map_err(err)?;
    }
    Ok(())
}

fn ttf_figure(r: &ExperimentResults, path: &Path) -> Result<()> {
    let rows = &r.methods.ttf;
    let loads: Vec<String> = unique(rows.iter().map(|c| c.load.clone()));
    let methods: Vec<String> = unique(rows.iter().map(|c| c.method.display()));
    let cols = [
        ("flat", false),
        ("flat", true),
        ("random", false),
        ("random", true),
    ];
    let groups: Vec<String> = cols
        .iter()
        .map(|(t, p)| format!("{t}{}", if *p { "+push" } else { "" }))
        .collect();
    let panels_w = 420 * loads.len().max(1) as u32;
    let root = SVGBackend::new(path, (panels_w + LEGEND_W, 380)).into_drawing_area();
    root.fill(&WHITE).map_err(err)?;
    let (left, legend) = root.split_horizontally(panels_w);
    let panels = left.split_evenly((1, loads.len().max(1)));
    let mut any_paper = false;
    for (load, area) in loads.iter().zip(panels.iter()) {
        let cell = |g: usize, s: usize| {
            rows.iter().find(|c| {
                &c.load == load
                    && c.method.display() == methods[s]
                    && c.terrain == cols[g].0
                    && c.push == cols[g].1
            })
        };
        // the paper's number is kept with the run its method is named after
        let paper = |g: usize, s: usize| {
            let label = &cell(g, s)?.method.label;
            r.ttf
                .iter()
                .find(|t| {
                    &t.method == label
                        && &t.load == load
                        && t.terrain == cols[g].0
                        && t.push == cols[g].1
                })
                .and_then(|t| t.paper)
        };
        any_paper |= (0..groups.len()).any(|g| (0..methods.len()).any(|s| paper(g, s).is_some()));
        let data = BarData {
            value: &|g, s| cell(g, s).map(|c| c.ttf),
            seeds: &|g, s| cell(g, s).map_or(Vec::new(), |c| c.per_seed.clone()),
            paper: &paper,
        };
        bars(
            area,
            (&format!("TTF, {load}"), "time to fall"),
            &groups,
            &methods,
            &data,
            1.05,
        )?;
    }
    bar_legend(&legend, &methods, any_paper)?;
    root.present().map_err(err)
}

fn platform_figure(r: &ExperimentResults, path: &Path) -> Result<()> {
    let rows = &r.methods.platform;
    let heights: Vec<String> = unique(rows.iter().map(|c| format!("{:.2} m", c.height_m)));
    let methods: Vec<String> = unique(rows.iter().map(|c| c.method.display()));
    let root = SVGBackend::new(path, (640 + LEGEND_W, 400)).into_drawing_area();
    root.fill(&WHITE).map_err(err)?;
    let (left, legend) = root.split_horizontally(640);
    let cell = |g: usize, s: usize| {
        rows.iter().find(|c| {
            format!("{:.2} m", c.height_m) == heights[g] && c.method.display() == methods[s]
        })
    };
    let paper = |g: usize, s: usize| {
        let c = cell(g, s)?;
        r.platform
            .iter()
            .find(|p| p.method == c.method.label && p.height_m == c.height_m)
            .and_then(|p| p.paper)
    };
    let any_paper = (0..heights.len()).any(|g| (0..methods.len()).any(|s| paper(g, s).is_some()));
    let data = BarData {
        value: &|g, s| cell(g, s).map(|c| c.success_pct),
        seeds: &|g, s| cell(g, s).map_or(Vec::new(), |c| c.per_seed.clone()),
        paper: &paper,
    };
    bars(
        &left,
        ("Walking off a platform", "success %"),
        &heights,
        &methods,
        &data,
        105.0,
    )?;
    bar_legend(&legend, &methods, any_paper)?;
    root.present().map_err(err)
}

fn race_figure(r: &ExperimentResults, path: &Path) -> Result<()> {
    let groups = vec!["q0.25".to_string(), "q0.5".into(), "q0.75".into()];
    let rows = &r.methods.race;
    let methods: Vec<String> = rows.iter().map(|c| c.method.display()).collect();
    let highest = rows
        .iter()
        .flat_map(|c| {
            [c.q25.hi, c.q50.hi, c.q75.hi]
                .into_iter()
                .chain(c.per_seed.iter().flatten().copied())
        })
        .fold(1e-6, f64::max);
    let root = SVGBackend::new(path, (720 + LEGEND_W, 420)).into_drawing_area();
    root.fill(&WHITE).map_err(err)?;
    let (left, legend) = root.split_horizontally(720);
    let data = BarData {
        value: &|g, s| rows.get(s).map(|c| [c.q25, c.q50, c.q75][g]),
        seeds: &|g, s| {
            rows.get(s)
                .map_or(Vec::new(), |c| c.per_seed.iter().map(|q| q[g]).collect())
        },
        paper: &|_, _| None,
    };
    bars(
        &left,
        ("Race track returns", "episode return"),
        &groups,
        &methods,
        &data,
        highest * 1.15,
    )?;
    bar_legend(&legend, &methods, false)?;
    root.present().map_err(err)
}

/// One panel per meta controller, stacked (drawn only when there is one).
fn race_iqr_figure(r: &ExperimentResults, path: &Path) -> Result<()> {
    let root = SVGBackend::new(path, (820, 380 * r.meta.len().max(1) as u32)).into_drawing_area();
    root.fill(&WHITE).map_err(err)?;
    for (m, area) in r
        .meta
        .iter()
        .zip(root.split_evenly((r.meta.len().max(1), 1)))
    {
        race_iqr_panel(m, &area)?;
    }
    root.present().map_err(err)
}

fn race_iqr_panel<DB: DrawingBackend>(
    m: &super::results::MetaSummary,
    root: &DrawingArea<DB, plotters::coord::Shift>,
) -> Result<()>
where
    DB::ErrorType: 'static,
{
    let bins = &m.iqr_by_x;
    let x_max = bins.iter().map(|b| b.x0_m + 0.5).fold(1.0, f64::max);
    let iqr_max = bins.iter().map(|b| b.mean_iqr).fold(1e-6, f64::max) * 1.15;
    let mut chart = ChartBuilder::on(root)
        .caption(
            format!("{}'s critic IQR along the race track", m.risky),
            ("sans-serif", 18),
        )
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(55)
        .right_y_label_area_size(55)
        .build_cartesian_2d(0.0..x_max, 0.0..iqr_max)
        .map_err(err)?
        .set_secondary_coord(0.0..x_max, 0.0..1.0);
    chart
        .configure_mesh()
        .x_desc("trunk x (m)")
        .y_desc("mean IQR")
        .draw()
        .map_err(err)?;
    chart
        .configure_secondary_axes()
        .y_desc("fraction on the safe policy")
        .draw()
        .map_err(err)?;
    chart
        .draw_series(LineSeries::new(
            bins.iter().map(|b| (b.x0_m + 0.25, b.mean_iqr)),
            PALETTE[0].stroke_width(2),
        ))
        .map_err(err)?
        .label("IQR (left axis)")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 12, y)], PALETTE[0].stroke_width(2)));
    chart
        .draw_secondary_series(LineSeries::new(
            bins.iter().map(|b| (b.x0_m + 0.25, b.safe_fraction)),
            PALETTE[3].stroke_width(2),
        ))
        .map_err(err)?
        .label(format!("{} on {} (right axis)", m.label, m.safe))
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 12, y)], PALETTE[3].stroke_width(2)));
    chart
        .configure_series_labels()
        .border_style(BLACK)
        .background_style(WHITE.mix(0.8))
        .draw()
        .map_err(err)?;
    Ok(())
}

pub(super) fn unique(it: impl Iterator<Item = String>) -> Vec<String> {
    let mut out: Vec<String> = Vec::new();
    for s in it {
        if !out.contains(&s) {
            out.push(s);
        }
    }
    out
}

/// One figure of an experiment's results.
#[derive(Clone, Debug, PartialEq)]
pub enum Figure {
    /// A robustness curve: an entry of [`CURVE_FIGURES`].
    Curve(&'static CurveFigure),
    Ttf,
    Platform,
    Race,
    RaceIqr,
    /// A benchmark's figure: the benchmark's name and the figure.
    Benchmark(String, FigureEntry),
}

impl Figure {
    pub fn file_name(&self) -> String {
        match self {
            Figure::Curve(c) => format!("curve_{}.svg", c.0),
            Figure::Ttf => "ttf.svg".into(),
            Figure::Platform => "platform.svg".into(),
            Figure::Race => "race.svg".into(),
            Figure::RaceIqr => "race_iqr.svg".into(),
            Figure::Benchmark(_, f) => f.file.clone(),
        }
    }

    /// What the figure shows, as the results' README lists it.
    pub fn shows(&self) -> &str {
        match self {
            Figure::Curve(c) => c.2,
            Figure::Ttf => "TTF per cell and method, seeds pooled, with intervals and a dot per seed (table I)",
            Figure::Platform => "platform success per height and method, seeds pooled, a dot per seed (table II)",
            Figure::Race => "race return quantiles per method (seeds pooled, a dot per seed) and the meta controller",
            Figure::RaceIqr => "the risk-neutral critic's IQR and the meta controller's use of the safe policy along the race track (the paper's fig. 4, left)",
            Figure::Benchmark(_, f) => &f.shows,
        }
    }

    fn draw(&self, r: &ExperimentResults, path: &Path) -> Result<()> {
        match self {
            Figure::Curve(c) => super::curve_plots::curve_figure(r, c, path),
            Figure::Ttf => ttf_figure(r, path),
            Figure::Platform => platform_figure(r, path),
            Figure::Race => race_figure(r, path),
            Figure::RaceIqr => race_iqr_figure(r, path),
            Figure::Benchmark(name, f) => r.benchmarks.draw(name, &f.file, path),
        }
    }
}

/// The figures of `r`, in the order the README lists them: the robustness
/// curves first (one per benchmark with points), then the rung-0 tables'
/// figures; the IQR figure only when the experiment has a meta controller; last
/// each benchmark's (`[commands]`: each method's command map).
/// The one list both [`write_all`] and the README read.
pub fn figures(r: &ExperimentResults) -> Vec<Figure> {
    let curves = CURVE_FIGURES
        .iter()
        .filter(|c| r.curves.iter().any(|p| p.metric == c.1))
        .map(Figure::Curve);
    let meta = (!r.meta.is_empty()).then_some(Figure::RaceIqr);
    let benchmarks = r
        .benchmarks
        .figures()
        .into_iter()
        .map(|(name, f)| Figure::Benchmark(name, f));
    curves
        .chain([Figure::Ttf, Figure::Platform, Figure::Race])
        .chain(meta)
        .chain(benchmarks)
        .collect()
}

/// Draws every figure of [`figures`] into `dir`.
pub fn write_all(r: &ExperimentResults, dir: &Path) -> Result<()> {
    for f in figures(r) {
        f.draw(r, &dir.join(f.file_name()))?;
    }
    Ok(())
}
