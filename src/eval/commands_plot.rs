//! The command map as an SVG heat map (plotters): one panel per vy value, vx
//! across and yaw rate up, each cell coloured by its fall rate (white 0% to dark
//! red 100%) with its fall percentage and linear tracking written in it, a black
//! frame around each cell that fails the safety threshold, and a colour bar.

use std::path::Path;

use anyhow::{anyhow, Result};
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};

use super::commands::{Axis, CommandMap, SafetyThreshold};

/// Side of one panel (px), panels per row, width of the colour bar column (px).
const PANEL_PX: u32 = 340;
const PANELS_PER_ROW: usize = 5;
const COLOUR_BAR_W: u32 = 120;
/// Narrowest figure (px): room for the title's two lines.
const MIN_WIDTH_PX: u32 = 560;
/// Width of the frame around a cell failing the threshold (px).
pub const FAIL_FRAME_PX: u32 = 3;
/// Height of the title band above the panels (px).
const TITLE_H: u32 = 44;

fn err<E: std::fmt::Display>(e: E) -> anyhow::Error {
    anyhow!("drawing the command map: {e}")
}

/// The colour of fall rate `rate` in [0, 1]: white to dark red.
pub fn fall_colour(rate: f64) -> RGBColor {
    let r = rate.clamp(0.0, 1.0);
    let lerp = |a: f64, b: f64| (a + (b - a) * r).round() as u8;
    RGBColor(lerp(255.0, 165.0), lerp(255.0, 0.0), lerp(255.0, 38.0))
}

/// Writes the heat map of `map` to `path` (SVG), a frame around each cell failing `t`.
pub fn write_command_map_svg(map: &CommandMap, t: &SafetyThreshold, path: &Path) -> Result<()> {
    let panels = map.grid.vy_mps.len().max(1);
    let cols = panels.min(PANELS_PER_ROW);
    let rows = panels.div_ceil(PANELS_PER_ROW);
    let width = (PANEL_PX * cols as u32 + COLOUR_BAR_W).max(MIN_WIDTH_PX);
    let height = PANEL_PX * rows as u32 + TITLE_H;
    let root = SVGBackend::new(path, (width, height)).into_drawing_area();
    root.fill(&WHITE).map_err(err)?;
    let (title, body) = root.split_vertically(TITLE_H);
    let style = ("sans-serif", 13).into_font().color(&BLACK);
    let lines = [
        format!(
            "Fall rate per command: {}, {} robots per cell",
            map.options.describe_short(),
            map.options.robots
        ),
        format!(
            "in each cell: fall rate, linear tracking below; a black frame: fails {}",
            t.describe()
        ),
    ];
    for (k, line) in lines.into_iter().enumerate() {
        title
            .draw(&Text::new(line, (10, 6 + 16 * k as i32), style.clone()))
            .map_err(err)?;
    }
    let (grid_area, bar) = body.split_horizontally(PANEL_PX * cols as u32);
    let areas = grid_area.split_evenly((rows, cols));
    for (&vy, area) in map.grid.vy_mps.iter().zip(areas.iter()) {
        panel(map, t, vy, area)?;
    }
    colour_bar(&bar)?;
    root.present().map_err(err)
}

/// The label of value `x` on an axis of `values` drawn as cells 0..n (a label at
/// each cell's centre, none elsewhere).
fn cell_label(values: &[f64], x: f64) -> String {
    let k = x.floor();
    if k < 0.0 || (x - k - 0.5).abs() > 0.26 {
        return String::new();
    }
    values
        .get(k as usize)
        .map_or(String::new(), |v| format!("{v:.2}"))
}

fn panel<DB: DrawingBackend>(
    map: &CommandMap,
    t: &SafetyThreshold,
    vy: f64,
    area: &DrawingArea<DB, Shift>,
) -> Result<()>
where
    DB::ErrorType: 'static,
{
    let vx = map.grid.axis(Axis::Vx).to_vec();
    let yaw = map.grid.axis(Axis::Yaw).to_vec();
    let (nx, ny) = (vx.len() as f64, yaw.len() as f64);
    let mut chart = ChartBuilder::on(area)
        .caption(format!("vy = {vy:+.2} m/s"), ("sans-serif", 16))
        .margin(10)
        .x_label_area_size(38)
        .y_label_area_size(48)
        .build_cartesian_2d(0.0..nx, 0.0..ny)
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
    let centred = ("sans-serif", 12).into_font().color(&BLACK).pos(middle);
    let small = ("sans-serif", 10)
        .into_font()
        .color(&BLACK.mix(0.6))
        .pos(middle);
    for (i, &x) in vx.iter().enumerate() {
        for (j, &w) in yaw.iter().enumerate() {
            let Some(c) = map.cell([x, vy, w]) else {
                continue;
            };
            let (x0, y0) = (i as f64, j as f64);
            chart
                .draw_series([Rectangle::new(
                    [(x0, y0), (x0 + 1.0, y0 + 1.0)],
                    fall_colour(c.fall_rate.value).filled(),
                )])
                .map_err(err)?;
            chart
                .draw_series([Rectangle::new(
                    [(x0, y0), (x0 + 1.0, y0 + 1.0)],
                    BLACK.mix(0.25).stroke_width(1),
                )])
                .map_err(err)?;
            if !c.is_safe(t) {
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
                        format!("{:.0}%", 100.0 * c.fall_rate.value),
                        (x0 + 0.5, y0 + 0.62),
                        centred.clone(),
                    ),
                    Text::new(
                        format!("{:.2}", c.lin_tracking.value),
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn colours_run_from_white_to_dark_red_and_labels_sit_at_cell_centres() {
        assert_eq!(fall_colour(0.0), RGBColor(255, 255, 255));
        assert_eq!(fall_colour(1.0), RGBColor(165, 0, 38));
        assert_eq!(fall_colour(7.0), fall_colour(1.0));
        let v = [-1.0, 0.0, 1.0];
        assert_eq!(cell_label(&v, 0.5), "-1.00");
        assert_eq!(cell_label(&v, 2.5), "1.00");
        assert_eq!(cell_label(&v, 1.0), "");
        assert_eq!(cell_label(&v, 3.5), "");
    }
}
