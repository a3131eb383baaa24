//! The viewer layouts, sent with every recording (the Rust SDK builds blueprints),
//! and written as `.rbl` files for recordings made without one
//! (`rerun file.rrd viz/rall-play.rbl`).
//!
//! The 3D view's eye follows the robot: an `EyeControls3D` view property tracking
//! `world/robot/trunk/follow` from about a metre behind it. The plots have no
//! legends (`PlotLegend` hidden): a legend inside a small plot covers its lines, so
//! the view titles say what is drawn, the velocity lines have the colours of the
//! 3D arrows, and hovering a line names it. rerun 0.36's Rust blueprint builder
//! cannot set view properties, so [`Layout::send`] adds them to the builder's
//! blueprint messages before sending them (one blueprint, one activation, exactly
//! as the builder would).

use anyhow::{Context, Result};
use rerun::blueprint::components::Eye3DKind;
use rerun::blueprint::components::{PanelState, PlayState};
use rerun::blueprint::{
    BarChartView, Blueprint, BlueprintActivation, BlueprintPanel, ContainerLike, Horizontal,
    SelectionPanel, Spatial3DView, Tabs, TextLogView, TimePanel, TimeSeriesView, Vertical,
};
use rerun::external::re_sdk_types::blueprint::archetypes::{EyeControls3D, PlotLegend};
use rerun::log::LogMsg;
use rerun::{RecordingStream, RecordingStreamBuilder};

/// Application id of `rall play` recordings (a blueprint applies to one application).
pub const PLAY_APP_ID: &str = "rall-play";
/// Application id of `rall train --rerun-*` recordings.
pub const TRAIN_APP_ID: &str = "rall-train";

/// A view property the builder cannot set, logged at `{view}/{name}`.
enum ViewProperty {
    Eye(Box<EyeControls3D>),
    Legend(PlotLegend),
}

/// View properties by blueprint path of their view.
type Properties = Vec<(String, ViewProperty)>;

/// A time series view of `origin` without a legend.
fn series(name: &str, origin: &str, props: &mut Properties) -> ContainerLike {
    let view: ContainerLike = TimeSeriesView::new(name).with_origin(origin).into();
    hide_legend(&view, props);
    view
}

/// A training metric's view: a legend names its terms (reward terms, losses).
fn training_series(name: &str, origin: &str) -> ContainerLike {
    TimeSeriesView::new(name).with_origin(origin).into()
}

fn hide_legend(view: &ContainerLike, props: &mut Properties) {
    if let ContainerLike::View(v) = view {
        props.push((
            v.blueprint_path().to_string(),
            ViewProperty::Legend(PlotLegend::update_fields().with_visible(false)),
        ));
    }
}

/// The entity the 3D view's eye follows: invisible points around the trunk
/// (`episode::log_follow_frame`), whose bounding box sets how far the eye stays.
pub const FOLLOWED_ENTITY: &str = "world/robot/trunk/follow";
/// Where the eye starts (world, m): behind, to the right of and above the spawn
/// point, looking at the trunk; it then keeps this offset as the robot walks.
const EYE_POSITION_M: [f32; 3] = [-0.8, -0.8, 0.6];
const EYE_TARGET_M: [f32; 3] = [0.0, 0.0, 0.3];

/// A viewer layout: the blueprint and its views' properties (3D eyes, legends).
pub struct Layout {
    blueprint: Blueprint,
    props: Properties,
}

impl Layout {
    /// The same layout, opened at the recording's last frame instead of playing it
    /// from the start (the time panel follows the latest data): where an episode
    /// ended, and headless screenshots of it (`viz/screenshot.sh`).
    pub fn opened_at_end(mut self) -> Self {
        self.blueprint = self
            .blueprint
            .with_time_panel(collapsed_time_panel().with_play_state(PlayState::Following));
        self
    }

    /// Sends the layout through `rec` (a recording or a blueprint file) and
    /// activates it as the default.
    pub fn send(&self, rec: &RecordingStream) -> Result<()> {
        let app = rec
            .store_info()
            .map(|i| i.application_id().clone())
            .context("the recording has no store info")?;
        // The builder's messages, captured in memory.
        let (mem, storage) = RecordingStreamBuilder::new(app.clone())
            .blueprint()
            .memory()
            .context("blueprint memory stream")?;
        self.blueprint
            .send(
                &mem,
                BlueprintActivation {
                    make_active: true,
                    make_default: true,
                },
            )
            .context("building the blueprint")?;
        mem.flush_blocking().context("flushing the blueprint")?;
        let msgs = storage.take();
        let cmd = msgs
            .iter()
            .find_map(|m| match m {
                LogMsg::BlueprintActivationCommand(c) => Some(c.clone()),
                _ => None,
            })
            .context("the blueprint builder sent no activation")?;
        let id = cmd.blueprint_id.clone();
        let mut out: Vec<LogMsg> = msgs
            .into_iter()
            .filter(|m| m.store_id() == &id && !matches!(m, LogMsg::BlueprintActivationCommand(_)))
            .collect();
        // The view properties, logged into that same blueprint store.
        let (prop, prop_storage) = RecordingStreamBuilder::new(app)
            .recording_id(id.recording_id().clone())
            .blueprint()
            .memory()
            .context("blueprint memory stream")?;
        prop.set_time_sequence("blueprint", 0);
        for (view, p) in &self.props {
            match p {
                ViewProperty::Eye(eye) => prop.log(format!("{view}/EyeControls3D"), &**eye),
                ViewProperty::Legend(legend) => prop.log(format!("{view}/PlotLegend"), legend),
            }
            .context("logging a view property")?;
        }
        prop.flush_blocking()
            .context("flushing the view properties")?;
        out.extend(
            prop_storage
                .take()
                .into_iter()
                .filter(|m| matches!(m, LogMsg::ArrowMsg(..)) && m.store_id() == &id),
        );
        rec.send_blueprint(out, cmd);
        Ok(())
    }
}

/// A 3D view of `world` whose eye frames and follows the robot.
fn robot_view(props: &mut Properties) -> ContainerLike {
    let view: ContainerLike =
        Spatial3DView::new("robot; arrows: command green, measured velocity blue, push red")
            .with_origin("world")
            .into();
    if let ContainerLike::View(v) = &view {
        props.push((
            v.blueprint_path().to_string(),
            ViewProperty::Eye(Box::new(
                EyeControls3D::new()
                    .with_kind(Eye3DKind::Orbital)
                    .with_position(EYE_POSITION_M)
                    .with_look_target(EYE_TARGET_M)
                    .with_tracking_entity(FOLLOWED_ENTITY),
            )),
        ));
    }
    view
}

/// `"{title} (0 a, 1 b, ...)"`: series named by the level they are drawn at.
fn levels_title(title: &str, names: impl IntoIterator<Item = impl AsRef<str>>) -> String {
    let levels: Vec<String> = names
        .into_iter()
        .enumerate()
        .map(|(k, n)| format!("{k} {}", n.as_ref()))
        .collect();
    format!("{title} ({})", levels.join(", "))
}

/// A risk term's name, short enough for a tab title (`joint_velocity` is `vel`).
fn short_term_name(name: &str) -> &str {
    match name.rsplit('_').next().unwrap_or(name) {
        "velocity" => "vel",
        "acceleration" => "acc",
        last => last,
    }
}

/// The episode panels: 3D robot and terrain, events, the quantile bar chart, mean and
/// CVaR, IQR, velocities (command vs measured), torques, contacts, risk crossings.
fn episode_layout(props: &mut Properties) -> ContainerLike {
    let left = Vertical::new([
        robot_view(props),
        TextLogView::new("events").with_origin("events").into(),
    ])
    .with_row_shares([3.0, 1.0]);
    let velocity = Horizontal::new([
        series("vx (m/s)", "plots/velocity/vx", props),
        series("vy (m/s)", "plots/velocity/vy", props),
        series("yaw rate (rad/s)", "plots/velocity/yaw_rate", props),
    ]);
    let quantiles: ContainerLike =
        BarChartView::new("Z_tau(s) minus its mean (y) at quantile tau (x, 0 to 1)")
            .with_origin("value/quantiles")
            .into();
    hide_legend(&quantiles, props);
    let right = Vertical::new([
        quantiles,
        Horizontal::new([
            series("value: mean (white), CVaR (orange)", "value/stats", props),
            series("IQR = Z_0.75 - Z_0.25", "value/iqr", props),
        ])
        .into(),
        velocity.into(),
        Tabs::new([
            series("torques (N m)", "plots/torques", props),
            series(
                &levels_title("contacts", crate::robot::LEGS),
                "plots/contacts",
                props,
            ),
            series(
                &levels_title(
                    "risk crossed",
                    crate::env::risk::RISK_TERMS
                        .iter()
                        .map(|t| short_term_name(t.name)),
                ),
                "plots/risk_crossed",
                props,
            ),
        ])
        .into(),
    ]);
    Horizontal::new([left.into(), right.into()])
        .with_column_shares([1.2, 1.0])
        .into()
}

fn collapsed_time_panel() -> TimePanel {
    TimePanel::new().with_state(PanelState::Collapsed)
}

/// `root` with rerun's blueprint, selection and time panels collapsed, so the views
/// get the whole window (the panels open from the viewer's top bar; the collapsed
/// time panel keeps its play controls and time slider).
fn collapsed_panels(root: impl Into<ContainerLike>) -> Blueprint {
    Blueprint::new(root)
        .with_auto_views(false)
        .with_blueprint_panel(BlueprintPanel::new().with_state(PanelState::Collapsed))
        .with_selection_panel(SelectionPanel::new().with_state(PanelState::Collapsed))
        .with_time_panel(collapsed_time_panel())
}

/// Layout of `rall play` recordings.
pub fn play_blueprint() -> Layout {
    let mut props = Vec::new();
    let blueprint = collapsed_panels(episode_layout(&mut props));
    Layout { blueprint, props }
}

/// Layout of training recordings: the metrics, and the evaluation episodes.
pub fn train_blueprint() -> Layout {
    let mut props = Vec::new();
    let metrics = Vertical::new([
        Horizontal::new([
            training_series("reward terms (per episode)", "train/reward_terms"),
            training_series("episode return", "train/episode/return"),
            training_series("episode length (steps)", "train/episode/length"),
        ])
        .into(),
        Horizontal::new([
            training_series("terrain level", "train/terrain_level"),
            training_series("falls (fraction)", "train/episode/fall_fraction"),
            training_series("risk penalties fired", "train/risk_fired"),
        ])
        .into(),
        Horizontal::new([
            training_series("losses", "train/loss"),
            training_series("learning rate", "train/learning_rate"),
            training_series("action std", "train/std"),
            training_series("env steps/s", "train/steps_per_s"),
        ])
        .into(),
    ])
    .with_name("training");
    let eval = Vertical::new([episode_layout(&mut props)]).with_name("evaluation episodes");
    let blueprint = collapsed_panels(Tabs::new([metrics.into(), eval.into()]));
    Layout { blueprint, props }
}
