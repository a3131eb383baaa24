//! A method's command map over its seeds as an SVG heat map (plotters), in the
//! style of `rall eval commands --figure`: one panel per vy value, vx across and
//! yaw rate up, each cell coloured by its fall rate averaged over the method's
//! seeds (white 0% to dark red 100%), with that rate and the number of seeds in
//! which the cell is safe written in it, and a black frame around each cell that
//! some seed fails.

use std::path::Path;

use anyhow::{anyhow, Result};
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};

use super::commands::{CommandCell, CommandsResult, MethodCommands};
use crate::eval::commands::Axis;
use crate::eval::commands_plot::{fall_colour, FAIL_FRAME_PX};

/// Side of one panel (px), panels per row, width of the colour bar (px), height
/// of the title band (px) and the narrowest figure (px).
const PANEL_PX: u32 = 340;
const PANELS_PER_ROW: usize = 5;
const COLOUR_BAR_W: u32 = 120;
const TITLE_H: u32 = 44;
const MIN_WIDTH_PX: u32 = 880;

fn err<E: std::fmt::Display>(e: E) -> anyhow::Error {
    anyhow!("drawing a command map: {e}")
}

/// One command's cells over the method's seeds.
struct Pooled {
    /// Mean over seeds of the cell's fall rate.
    fall_rate: f64,
    /// Seeds in which the cell is safe, and seeds.
    safe: usize,
    seeds: usize,
}

/// The cells of command `c` in each of `m`'s seeds, pooled.
fn pooled(r: &CommandsResult, m: &MethodCommands, c: [f64; 3]) -> Option<Pooled> {
    let cells: Vec<&CommandCell> = r
        .runs
        .iter()
        .filter(|run| m.method.seeds.contains(&run.label))
        .filter_map(|run| run.cells.iter().find(|x| x.command() == c))
        .collect();
    if cells.is_empty() {
        return None;
    }
    let n = cells.len();
    Some(Pooled {
        fall_rate: cells.iter().map(|x| x.fall_rate().value).sum::<f64>() / n as f64,
        safe: cells.iter().filter(|x| x.is_safe(&r.threshold)).count(),
        seeds: n,
    })
}

/// Writes method `m`'s map (over its seeds) to `path` (SVG).
pub fn commands_figure(r: &CommandsResult, m: &MethodCommands, path: &Path) -> Result<()> {
    let panels = r.grid.vy_mps.len().max(1);
    let cols = panels.min(PANELS_PER_ROW);
    let rows = panels.div_ceil(PANELS_PER_ROW);
    let width = (PANEL_PX * cols as u32 + COLOUR_BAR_W).max(MIN_WIDTH_PX);
    let height = PANEL_PX * rows as u32 + TITLE_H;
    let root = SVGBackend::new(path, (width, height)).into_drawing_area();
    root.fill(&WHITE).map_err(err)?;
    let (title, body) = root.split_vertically(TITLE_H);
    let style = ("sans-serif", 13).into_font().color(&BLACK);
    let seeds = m.method.seeds.len();
    let lines = [
        format!(
            "{}: fall rate per command, mean over {seeds} seed{}; {}, {} robots per cell and seed",
            m.method.label,
            if seeds == 1 { "" } else { "s" },
            r.conditions,
            r.robots
        ),
        format!(
            "in each cell: mean fall rate, seeds in which it is safe below; a black frame: some seed fails {}",
            r.threshold.describe()
        ),
    ];
    for (k, line) in lines.into_iter().enumerate() {
        title
            .draw(&Text::new(line, (10, 6 + 16 * k as i32), style.clone()))
            .map_err(err)?;
    }
    let (grid_area, bar) = body.split_horizontally(PANEL_PX * cols as u32);
    let areas = grid_area.split_evenly((rows, cols));
    for (&vy, area) in r.grid.vy_mps.iter().zip(areas.iter()) {
        panel(r, m, vy, area)?;
    }
    colour_bar(&bar)?;
    root.present().map_err(err)
}

/// The label of value `x` on an axis of `values` drawn as cells 0..n: a label at
/// each cell's centre, none elsewhere.
fn cell_label(values: &[f64], x: f64) -> String {
    let k = x.floor();
    if k < 0.0 || (x - k - 0.5).abs() > 0.26 {
        return String::new();
    }
    values
        .get(k as usize)
        .map_or(String::new(), |v| format!("{v:.2}"))
}

/// One vy value's panel: a cell per (vx, yaw rate).
fn panel<DB: DrawingBackend>(
    r: &CommandsResult,
    m: &MethodCommands,
    vy: f64,
    area: &DrawingArea<DB, Shift>,
) -> Result<()>
where
    DB::ErrorType: 'static,
{
    let vx = r.grid.vx_mps.clone();
    let yaw = r.grid.yaw_rate_rad_s.clone();
    let mut chart = ChartBuilder::on(area)
        .caption(format!("vy = {vy:+.2} m/s"), ("sans-serif", 16))
        .margin(10)
        .x_label_area_size(38)
        .y_label_area_size(48)
        .build_cartesian_2d(0.0..vx.len() as f64, 0.0..yaw.len() as f64)
        .map_err(err)?;
    let (xs, ys) = (vx.clone(), yaw.clone());
    chart
        .configure_mesh()
        .disable_mesh()
        .x_labels(vx.len() * 2 + 1)
        .y_labels(yaw.len() * 2 + 1)
        .x_label_formatter(&move |x| cell_label(&xs, *x))
        .y_label_formatter(&move |y| cell_label(&ys, *y))
        .x_desc(Axis::Vx.label())
        .y_desc(Axis::Yaw.label())
        .draw()
        .map_err(err)?;
    let middle = Pos::new(HPos::Center, VPos::Center);
    let big = ("sans-serif", 12).into_font().color(&BLACK).pos(middle);
    let small = ("sans-serif", 10)
        .into_font()
        .color(&BLACK.mix(0.6))
        .pos(middle);
    for (i, &x) in vx.iter().enumerate() {
        for (j, &w) in yaw.iter().enumerate() {
            let Some(p) = pooled(r, m, [x, vy, w]) else {
                continue;
            };
            let (x0, y0) = (i as f64, j as f64);
            let square = [(x0, y0), (x0 + 1.0, y0 + 1.0)];
            chart
                .draw_series([
                    Rectangle::new(square, fall_colour(p.fall_rate).filled()),
                    Rectangle::new(square, BLACK.mix(0.25).stroke_width(1)),
                ])
                .map_err(err)?;
            if p.safe < p.seeds {
                let (a, b) = (0.05, 0.95);
                // a path, not a rectangle: the SVG backend draws rectangles 1 px wide
                let corners = [(a, a), (b, a), (b, b), (a, b), (a, a)];
                chart
                    .draw_series([PathElement::new(
                        corners.map(|(dx, dy)| (x0 + dx, y0 + dy)).to_vec(),
                        BLACK.stroke_width(FAIL_FRAME_PX),
                    )])
                    .map_err(err)?;
            }
            chart
                .draw_series([
                    Text::new(
                        format!("{:.0}%", 100.0 * p.fall_rate),
                        (x0 + 0.5, y0 + 0.62),
                        big.clone(),
                    ),
                    Text::new(
                        format!("{}/{} safe", p.safe, p.seeds),
                        (x0 + 0.5, y0 + 0.34),
                        small.clone(),
                    ),
                ])
                .map_err(err)?;
        }
    }
    Ok(())
}

/// The colour scale, 0% at the bottom to 100% at the top.
fn colour_bar<DB: DrawingBackend>(area: &DrawingArea<DB, Shift>) -> Result<()>
where
    DB::ErrorType: 'static,
{
    let style = ("sans-serif", 12).into_font().color(&BLACK);
    let (top, bottom, steps) = (40, 280, 20);
    let step_h = (bottom - top) / steps;
    area.draw(&Text::new("fall rate", (14, top - 26), style.clone()))
        .map_err(err)?;
    for k in 0..steps {
        let rate = 1.0 - k as f64 / (steps - 1) as f64;
        let y = top + k * step_h;
        area.draw(&Rectangle::new(
            [(14, y), (40, y + step_h)],
            fall_colour(rate).filled(),
        ))
        .map_err(err)?;
    }
    area.draw(&Rectangle::new(
        [(14, top), (40, top + steps * step_h)],
        BLACK.stroke_width(1),
    ))
    .map_err(err)?;
    for (label, y) in [("100%", top), ("50%", (top + bottom) / 2), ("0%", bottom)] {
        area.draw(&Text::new(label, (46, y - 6), style.clone()))
            .map_err(err)?;
    }
    Ok(())
}
