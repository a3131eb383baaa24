//! The viewer layouts, sent with every recording (the Rust SDK builds blueprints),
//! and written as `.rbl` files for recordings made without one
//! (`rerun file.rrd viz/rall-play.rbl`).

use std::path::Path;

use anyhow::{Context, Result};
use rerun::blueprint::{
    BarChartView, Blueprint, BlueprintActivation, ContainerLike, Horizontal, Spatial3DView, Tabs,
    TextLogView, TimeSeriesView, Vertical,
};

/// Application id of `rall play` recordings (a blueprint applies to one application).
pub const PLAY_APP_ID: &str = "rall-play";
/// Application id of `rall train --rerun-*` recordings.
pub const TRAIN_APP_ID: &str = "rall-train";

fn series(name: &str, origin: &str) -> ContainerLike {
    TimeSeriesView::new(name).with_origin(origin).into()
}

/// The episode panels: 3D robot and terrain, events, the quantile bar chart, mean and
/// CVaR, IQR, velocities (command vs measured), torques, contacts.
fn episode_layout() -> ContainerLike {
    let left = Vertical::new([
        Spatial3DView::new("robot").with_origin("world").into(),
        TextLogView::new("events").with_origin("events").into(),
    ])
    .with_row_shares([3.0, 1.0]);
    let velocity = Horizontal::new([
        series("vx (m/s): command, measured", "plots/velocity/vx"),
        series("vy (m/s): command, measured", "plots/velocity/vy"),
        series(
            "yaw rate (rad/s): command, measured",
            "plots/velocity/yaw_rate",
        ),
    ]);
    let right = Vertical::new([
        BarChartView::new("value distribution Z_tau(s)")
            .with_origin("value/quantiles")
            .into(),
        Horizontal::new([
            series("value: mean and CVaR", "value/stats"),
            series("IQR", "value/iqr"),
        ])
        .into(),
        velocity.into(),
        Tabs::new([
            series("joint torques (N m)", "plots/torques"),
            series("foot contacts", "plots/contacts"),
        ])
        .into(),
    ]);
    Horizontal::new([left.into(), right.into()])
        .with_column_shares([1.2, 1.0])
        .into()
}

/// Layout of `rall play` recordings.
pub fn play_blueprint() -> Blueprint {
    Blueprint::new(episode_layout()).with_auto_views(false)
}

/// Layout of training recordings: the metrics, and the evaluation episodes.
pub fn train_blueprint() -> Blueprint {
    let metrics = Vertical::new([
        Horizontal::new([
            series("reward terms (per episode)", "train/reward_terms"),
            series("episode return", "train/episode/return"),
            series("episode length (steps)", "train/episode/length"),
        ])
        .into(),
        Horizontal::new([
            series("terrain level", "train/terrain_level"),
            series("falls (fraction)", "train/episode/fall_fraction"),
            series("risk penalties fired", "train/risk_fired"),
        ])
        .into(),
        Horizontal::new([
            series("losses", "train/loss"),
            series("learning rate", "train/learning_rate"),
            series("action std", "train/std"),
            series("env steps/s", "train/steps_per_s"),
        ])
        .into(),
    ])
    .with_name("training");
    let eval = Vertical::new([episode_layout()]).with_name("evaluation episodes");
    Blueprint::new(Tabs::new([metrics.into(), eval.into()])).with_auto_views(false)
}

/// Writes `blueprint` for `application_id` as an `.rbl` file.
pub fn write_blueprint_file(
    path: &Path,
    application_id: &'static str,
    blueprint: Blueprint,
) -> Result<()> {
    let rec = rerun::RecordingStreamBuilder::new(application_id)
        .blueprint()
        .save(path)
        .with_context(|| format!("opening {}", path.display()))?;
    blueprint
        .send(
            &rec,
            BlueprintActivation {
                make_active: true,
                make_default: true,
            },
        )
        .context("writing the blueprint")?;
    super::sink::finish_recording(rec)
}
