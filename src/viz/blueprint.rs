//! The viewer layouts, sent with every recording (the Rust SDK builds blueprints),
//! and written as `.rbl` files for recordings made without one
//! (`rerun file.rrd viz/rall-play.rbl`).
//!
//! The 3D view's eye follows the robot: an `EyeControls3D` view property tracking
//! `world/robot/trunk/follow` from a few metres behind it. rerun 0.36's Rust blueprint
//! builder cannot set view properties, so [`Layout::send`] adds that property to
//! the builder's blueprint messages before sending them (one blueprint, one
//! activation, exactly as the builder would).

use anyhow::{Context, Result};
use rerun::blueprint::components::Eye3DKind;
use rerun::blueprint::components::{PanelState, PlayState};
use rerun::blueprint::{
    BarChartView, Blueprint, BlueprintActivation, BlueprintPanel, ContainerLike, Horizontal,
    SelectionPanel, Spatial3DView, Tabs, TextLogView, TimePanel, TimeSeriesView, Vertical,
};
use rerun::external::re_sdk_types::blueprint::archetypes::EyeControls3D;
use rerun::log::LogMsg;
use rerun::{RecordingStream, RecordingStreamBuilder};

/// Application id of `rall play` recordings (a blueprint applies to one application).
pub const PLAY_APP_ID: &str = "rall-play";
/// Application id of `rall train --rerun-*` recordings.
pub const TRAIN_APP_ID: &str = "rall-train";

fn series(name: &str, origin: &str) -> ContainerLike {
    TimeSeriesView::new(name).with_origin(origin).into()
}

/// The entity the 3D view's eye follows: invisible points around the trunk
/// (`episode::log_follow_frame`), whose bounding box sets how far the eye stays.
pub const FOLLOWED_ENTITY: &str = "world/robot/trunk/follow";
/// Where the eye starts (world, m): behind, to the right of and above the spawn
/// point, looking at the trunk; it then keeps this offset as the robot walks.
const EYE_POSITION_M: [f32; 3] = [-0.8, -0.8, 0.6];
const EYE_TARGET_M: [f32; 3] = [0.0, 0.0, 0.3];

/// A viewer layout: the blueprint and the eye of each 3D view (by blueprint path).
pub struct Layout {
    blueprint: Blueprint,
    eyes: Vec<(String, EyeControls3D)>,
}

impl Layout {
    /// The same layout, opened at the recording's last frame instead of playing it
    /// from the start (the time panel follows the latest data): where an episode
    /// ended, and headless screenshots of it (`viz/screenshot.sh`).
    pub fn opened_at_end(mut self) -> Self {
        self.blueprint = self
            .blueprint
            .with_time_panel(TimePanel::new().with_play_state(PlayState::Following));
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
        // The eyes, logged into that same blueprint store.
        let (eye, eye_storage) = RecordingStreamBuilder::new(app)
            .recording_id(id.recording_id().clone())
            .blueprint()
            .memory()
            .context("blueprint memory stream")?;
        eye.set_time_sequence("blueprint", 0);
        for (view, controls) in &self.eyes {
            eye.log(format!("{view}/EyeControls3D"), controls)
                .context("logging the 3D eye")?;
        }
        eye.flush_blocking().context("flushing the 3D eye")?;
        out.extend(
            eye_storage
                .take()
                .into_iter()
                .filter(|m| matches!(m, LogMsg::ArrowMsg(..)) && m.store_id() == &id),
        );
        rec.send_blueprint(out, cmd);
        Ok(())
    }
}

/// A 3D view of `world` whose eye frames and follows the robot.
fn robot_view(eyes: &mut Vec<(String, EyeControls3D)>) -> ContainerLike {
    let view: ContainerLike = Spatial3DView::new("robot").with_origin("world").into();
    if let ContainerLike::View(v) = &view {
        eyes.push((
            v.blueprint_path().to_string(),
            EyeControls3D::new()
                .with_kind(Eye3DKind::Orbital)
                .with_position(EYE_POSITION_M)
                .with_look_target(EYE_TARGET_M)
                .with_tracking_entity(FOLLOWED_ENTITY),
        ));
    }
    view
}

/// The episode panels: 3D robot and terrain, events, the quantile bar chart, mean and
/// CVaR, IQR, velocities (command vs measured), torques, contacts.
fn episode_layout(eyes: &mut Vec<(String, EyeControls3D)>) -> ContainerLike {
    let left = Vertical::new([
        robot_view(eyes),
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
            series(
                "risk thresholds crossed (term k at k + 0.8)",
                "plots/risk_crossed",
            ),
        ])
        .into(),
    ]);
    Horizontal::new([left.into(), right.into()])
        .with_column_shares([1.2, 1.0])
        .into()
}

/// `root` with rerun's blueprint and selection panels collapsed, so the views get
/// the whole window (the panels open from the viewer's top bar).
fn collapsed_panels(root: impl Into<ContainerLike>) -> Blueprint {
    Blueprint::new(root)
        .with_auto_views(false)
        .with_blueprint_panel(BlueprintPanel::new().with_state(PanelState::Collapsed))
        .with_selection_panel(SelectionPanel::new().with_state(PanelState::Collapsed))
}

/// Layout of `rall play` recordings.
pub fn play_blueprint() -> Layout {
    let mut eyes = Vec::new();
    let blueprint = collapsed_panels(episode_layout(&mut eyes));
    Layout { blueprint, eyes }
}

/// Layout of training recordings: the metrics, and the evaluation episodes.
pub fn train_blueprint() -> Layout {
    let mut eyes = Vec::new();
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
    let eval = Vertical::new([episode_layout(&mut eyes)]).with_name("evaluation episodes");
    let blueprint = collapsed_panels(Tabs::new([metrics.into(), eval.into()]));
    Layout { blueprint, eyes }
}
