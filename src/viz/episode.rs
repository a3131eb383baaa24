//! Logging one robot, step by step, to a rerun recording.
//!
//! Entity layout (the blueprint in [`super::blueprint`] refers to these paths):
//!
//! | path | what | when |
//! | --- | --- | --- |
//! | `world/robot/<body>` | `Transform3D` (world pose of the body) | every step |
//! | `world/robot/<body>/<geom>` | box / capsule / ellipsoid / cylinder in the body frame; a welded body's geoms (the feet) under its parent | static |
//! | `world/robot/trunk/follow` | invisible points: the box the 3D view's eye frames and follows | static |
//! | `world/terrain/chunk_<x>_<y>` | heightfield mesh, 8 m chunks, logged when the robot comes near | static |
//! | `world/ground` | a quad (flat ground) | static |
//! | `world/velocity` | arrows at the trunk: command (green), measured (blue) | every step |
//! | `world/push` | arrow at the trunk while a push acts (cleared after) | on pushes |
//! | `plots/velocity/{vx,vy,yaw_rate}` | scalars `[command, measured]` (body frame) | every step |
//! | `plots/torques` | 12 joint torques (N m) | every step |
//! | `plots/contacts` | foot contact, leg `i` drawn at `i + 0.8 * contact` | every step |
//! | `plots/risk_crossed` | risk thresholds crossed, term `k` drawn at `k + 0.8 * crossed` | every step |
//! | `value/quantiles` | `BarChart` of `Z_tau(s)` minus its mean on a midpoint tau grid, bars `1/n` wide over [0, 1] (IQN only) | every [`VALUE_EVERY_FRAMES`] frames |
//! | `value/stats` | scalars `[mean, CVaR_eta]` (scalar critic: `[V, V]`) | every [`VALUE_EVERY_FRAMES`] frames |
//! | `value/iqr` | `Z_0.75(s) - Z_0.25(s)` | every [`VALUE_EVERY_FRAMES`] frames |
//! | `events` | `TextLog`: episodes, fired risk penalties, pushes, falls, command changes | on events |
//!
//! Timelines: `sim_time` (seconds of simulated time, continuing across episodes),
//! `step` (policy steps), plus any extra constant sequence (e.g. `iteration` for
//! evaluation episodes during training).
//!
//! Per-step data is buffered and handed, every [`DEFAULT_FLUSH_STEPS`] policy steps,
//! to a worker thread that reads the critic for the whole batch (about 6x cheaper
//! per step than one observation at a time, on the worker's own core) and sends one
//! chunk per entity, while the simulation goes on; events and terrain go out at once
//! from the caller's thread. What a recording costs beyond that is rerun's: opening
//! the file (its layout is built on another thread, see [`super::sink`]), and at the
//! end encoding the last batch and writing the file's footer.

use std::collections::HashSet;
use std::sync::{mpsc, Arc};

use anyhow::{Context, Result};
use rerun::{RecordingStream, TimeColumn};

use super::convert::{self, Primitive, TriMesh};
use super::value::ValueProbe;
use crate::env::config::PushConfig;
use crate::env::risk::NUM_RISK_TERMS;
use crate::env::state::{roll_pitch_yaw, unit_quat};
use crate::env::terrain::Terrain;
use crate::env::{Env, StepResult};
use crate::learn::{ActorCritic, Learner};
use crate::robot::{Robot, LEGS};
use crate::sim::ObjKind;

/// Steps buffered before the columns are sent (5 s at 50 Hz): every flush costs a
/// chunk per entity, and the critic reads the whole batch at once.
pub const DEFAULT_FLUSH_STEPS: usize = 250;
/// By default the critic's readings (bar chart, mean/CVaR, IQR) are taken every this
/// many frames (10 Hz at a 50 Hz policy): a viewer needs no per-step resolution of the
/// value, and reading the critic was most of the logging cost.
pub const VALUE_EVERY_FRAMES: usize = 5;
/// Side of a terrain chunk in samples (8 m at 0.1 m).
const TERRAIN_CHUNK_SAMPLES: usize = 80;
/// Terrain chunks within this distance (m) of the trunk are logged.
const TERRAIN_RADIUS_M: f64 = 6.0;
/// Half side of the flat-ground quad (m).
const GROUND_HALF_EXTENT_M: f64 = 50.0;
/// Arrow length per newton of push force (m/N).
const PUSH_ARROW_M_PER_N: f32 = 0.005;

/// Per-step columns waiting to be sent.
#[derive(Default)]
struct Columns {
    time_s: Vec<f64>,
    step: Vec<i64>,
    /// Per body: translations and xyzw quaternions.
    body_pos: Vec<Vec<[f32; 3]>>,
    body_quat: Vec<Vec<[f32; 4]>>,
    vx: Vec<f64>,
    vy: Vec<f64>,
    wz: Vec<f64>,
    torques: Vec<f64>,
    contacts: Vec<f64>,
    /// Per frame and risk term: `k + 0.8 * crossed`.
    risk_crossed: Vec<f64>,
    arrows_origin: Vec<[f32; 3]>,
    arrows_vec: Vec<[f32; 3]>,
    /// Observations of every [`VALUE_EVERY_FRAMES`]-th frame (k x obs_dim), read by
    /// the critic at the flush, with their times.
    obs: Vec<f32>,
    value_time_s: Vec<f64>,
    value_step: Vec<i64>,
    extra_timeline: Option<(&'static str, i64)>,
}

impl Columns {
    fn len(&self) -> usize {
        self.time_s.len()
    }
    fn is_empty(&self) -> bool {
        self.time_s.is_empty()
    }
    /// Empty, with room for `bodies` bodies.
    fn reset(&mut self, bodies: usize) {
        *self = Columns {
            body_pos: vec![Vec::new(); bodies],
            body_quat: vec![Vec::new(); bodies],
            ..Default::default()
        };
    }
}

/// A heightfield the logger can draw: training terrain or a scenario's ground.
pub trait HeightGrid: Send + Sync {
    /// Samples along (x, y).
    fn grid_shape(&self) -> (usize, usize);
    /// World position of sample (0, 0) (m).
    fn grid_origin_m(&self) -> [f64; 2];
    /// Spacing between samples (m).
    fn horizontal_scale_m(&self) -> f64;
    /// Heights (m), row-major with rows along y.
    fn heights_m(&self) -> &[f32];
    /// (lowest, highest) height (m).
    fn height_range_m(&self) -> (f64, f64);
}

macro_rules! impl_height_grid {
    ($t:ty) => {
        impl HeightGrid for $t {
            fn grid_shape(&self) -> (usize, usize) {
                <$t>::grid_shape(self)
            }
            fn grid_origin_m(&self) -> [f64; 2] {
                <$t>::grid_origin_m(self)
            }
            fn horizontal_scale_m(&self) -> f64 {
                <$t>::horizontal_scale_m(self)
            }
            fn heights_m(&self) -> &[f32] {
                <$t>::heights_m(self)
            }
            fn height_range_m(&self) -> (f64, f64) {
                <$t>::height_range_m(self)
            }
        }
    };
}
impl_height_grid!(Terrain);
impl_height_grid!(crate::eval::ground::Ground);

/// Logs a robot (and its ground) to a recording; see the module docs for the paths.
pub struct EpisodeLogger {
    rec: RecordingStream,
    /// (body id, entity path) of every robot body.
    bodies: Vec<(usize, String)>,
    /// The policy of the current episode (the worker's critic).
    policy: Option<Arc<ActorCritic>>,
    worker: Worker,
    terrain: Option<Arc<dyn HeightGrid>>,
    logged_chunks: HashSet<(usize, usize)>,
    extra_timeline: Option<(&'static str, i64)>,
    cols: Columns,
    flush_steps: usize,
    /// Policy steps in the buffered batch.
    steps_in_batch: usize,
    time_s: f64,
    step: i64,
    /// Frames recorded (the critic is read on every `value_every`-th).
    frames: usize,
    value_every: usize,
    push_shown: bool,
    prev_base_vel_world: [f64; 3],
}

fn rgba(c: [f32; 4]) -> rerun::Color {
    let b = |v: f32| (v.clamp(0.0, 1.0) * 255.0).round() as u8;
    rerun::Color::from_unmultiplied_rgba(b(c[0]), b(c[1]), b(c[2]), b(c[3]))
}

fn log_mesh(rec: &RecordingStream, path: &str, m: &TriMesh) -> Result<()> {
    rec.log_static(
        path,
        &rerun::Mesh3D::new(m.positions.iter().copied())
            .with_vertex_normals(m.normals.iter().copied())
            .with_vertex_colors(
                m.colors
                    .iter()
                    .map(|c| rerun::Color::from_unmultiplied_rgba(c[0], c[1], c[2], c[3])),
            )
            .with_triangle_indices(m.triangles.iter().copied()),
    )?;
    Ok(())
}

/// Half extents (m, trunk frame) of the box the 3D view's eye frames: rerun's
/// tracking eye orbits at 1.5x the tracked entity's bounding-sphere radius, so this
/// box puts the eye about 0.85 m from the trunk: the robot about a third of the
/// view's height (at 1.2 m it was a quarter, at 2.4 m a sixth).
const FOLLOW_FRAME_HALF_M: [f32; 3] = [0.42, 0.32, 0.18];

/// The entity the eye tracks ([`super::blueprint::FOLLOWED_ENTITY`]): the corners of
/// [`FOLLOW_FRAME_HALF_M`] as zero-radius points in the trunk frame, invisible but
/// with a bounding box. rerun tracks an entity's own geometry, not its children's,
/// so the trunk body (a transform only) cannot be tracked, and its box geom alone
/// would put the eye 0.5 m from it.
fn log_follow_frame(rec: &RecordingStream, trunk_path: &str) -> Result<()> {
    let [x, y, z] = FOLLOW_FRAME_HALF_M;
    let corners: Vec<[f32; 3]> = (0..8)
        .map(|i| {
            let sign = |bit: usize| if i & bit == 0 { -1.0 } else { 1.0 };
            [sign(1) * x, sign(2) * y, sign(4) * z]
        })
        .collect();
    rec.log_static(
        format!("{trunk_path}/{FOLLOW_FRAME}"),
        &rerun::Points3D::new(corners).with_radii([0.0]),
    )?;
    Ok(())
}

/// Name of the follow frame's entity under the trunk.
const FOLLOW_FRAME: &str = "follow";

/// A rigid transform: `(pos, quat)` maps a child frame into its parent's
/// (quaternions w, x, y, z, as MuJoCo stores them).
#[derive(Debug, Clone, Copy, PartialEq)]
struct Pose {
    pos: [f64; 3],
    quat: [f64; 4],
}

impl Pose {
    const IDENTITY: Pose = Pose {
        pos: [0.0; 3],
        quat: [1.0, 0.0, 0.0, 0.0],
    };

    /// `inner`, a pose given in this frame, in the parent's.
    fn then(self, inner: Pose) -> Pose {
        let r = unit_quat(self.quat);
        let p = r * nalgebra::Vector3::from(inner.pos) + nalgebra::Vector3::from(self.pos);
        let q = (r * unit_quat(inner.quat)).into_inner();
        Pose {
            pos: [p.x, p.y, p.z],
            quat: [q.w, q.i, q.j, q.k],
        }
    }
}

/// The body whose transform draws body `b` (`b` itself, or for a body welded to its
/// parent the nearest ancestor with a joint, the world excepted) and `b`'s frame in it.
fn carrier(m: &crate::sim::Model, b: usize) -> (usize, Pose) {
    let mut pose = Pose::IDENTITY;
    let mut b = b;
    while b != 0 && m.body_joint_count(b) == 0 && m.body_parent(b) != 0 {
        pose = Pose {
            pos: m.body_pos_m()[b],
            quat: m.body_quat()[b],
        }
        .then(pose);
        b = m.body_parent(b);
    }
    (b, pose)
}

/// Entity path of body `b` under `world/robot`.
pub fn body_path(robot: &Robot, b: usize) -> String {
    let name = robot.model().name(ObjKind::Body, b);
    if name.is_empty() {
        format!("world/robot/body_{b}")
    } else {
        format!("world/robot/{name}")
    }
}

/// Logs the robot's geoms under the bodies that carry them (the world body's
/// as static ground); returns those bodies with their entity paths, in model order.
fn log_robot_geoms(rec: &RecordingStream, robot: &Robot) -> Result<Vec<(usize, String)>> {
    let m = robot.model();
    // A body welded to its parent (a foot to its calf) moves with it: its geoms are
    // drawn under the parent, which saves a transform per step.
    let carriers: Vec<(usize, Pose)> = (0..m.nbody()).map(|b| carrier(m, b)).collect();
    // Bodies that carry geoms (plus the trunk), in model order; the world body's
    // ground geoms are logged as terrain.
    let mut has_geom = vec![false; m.nbody()];
    for g in 0..m.ngeom() {
        has_geom[carriers[m.geom_body(g)].0] = true;
    }
    has_geom[robot.layout.trunk_body] = true;
    let bodies: Vec<(usize, String)> = has_geom
        .iter()
        .enumerate()
        .skip(1)
        .filter(|(_, h)| **h)
        .map(|(b, _)| (b, body_path(robot, b)))
        .collect();
    for g in 0..m.ngeom() {
        let (b, in_carrier) = carriers[m.geom_body(g)];
        let geom = in_carrier.then(Pose {
            pos: m.geom_pos()[g],
            quat: m.geom_quat()[g],
        });
        let Some(prim) =
            convert::geom_primitive(m.geom_shape(g), m.geom_size()[g], geom.pos, geom.quat)
        else {
            continue;
        };
        let name = m.name(ObjKind::Geom, g);
        let name = if name.is_empty() {
            format!("geom_{g}")
        } else {
            name.to_string()
        };
        let path = if b == 0 {
            format!("world/static/{name}")
        } else {
            format!("{}/{name}", body_path(robot, b))
        };
        log_primitive(rec, &path, &prim, rgba(m.geom_rgba()[g]))?;
    }
    Ok(bodies)
}

/// Colour of the velocity command, as an arrow and as a line.
const COMMAND_RGB: [u8; 3] = [40, 200, 60];
/// Colour of the measured velocity, as an arrow and as a line.
const MEASURED_RGB: [u8; 3] = [60, 120, 240];

fn colour([r, g, b]: [u8; 3]) -> rerun::Color {
    rerun::Color::from_rgb(r, g, b)
}

/// The static styles of the plots: series names, arrow colours, the quantile bars' taus.
fn log_plot_styles(rec: &RecordingStream, robot: &Robot, probe: &ValueProbe) -> Result<()> {
    let series =
        |names: &[&str]| rerun::SeriesLines::new().with_names(names.iter().map(|s| s.to_string()));
    // the plots have no legends: the velocity lines take the 3D arrows' colours,
    // the value lines the colours their view's title names
    for axis in ["vx", "vy", "yaw_rate"] {
        rec.log_static(
            format!("plots/velocity/{axis}"),
            &series(&["command", "measured"])
                .with_colors([colour(COMMAND_RGB), colour(MEASURED_RGB)])
                // the command, drawn first, stays visible under the measured line
                .with_widths([3.0, 1.0]),
        )?;
    }
    let joints: Vec<&str> = robot
        .layout
        .joint_names
        .iter()
        .map(|s| s.as_str())
        .collect();
    rec.log_static("plots/torques", &series(&joints))?;
    rec.log_static("plots/contacts", &series(&LEGS))?;
    let terms: Vec<&str> = crate::env::risk::RISK_TERMS
        .iter()
        .map(|t| t.name)
        .collect();
    rec.log_static("plots/risk_crossed", &series(&terms))?;
    rec.log_static(
        "value/stats",
        &series(&["mean", probe.label()]).with_colors([
            rerun::Color::from_rgb(230, 230, 230),
            rerun::Color::from_rgb(255, 150, 30),
        ]),
    )?;
    rec.log_static(
        "value/iqr",
        &series(&["IQR"]).with_colors([rerun::Color::from_rgb(230, 200, 60)]),
    )?;
    // Per-step data carries only what changes: the colours of the velocity
    // arrows and the taus of the bar chart are static.
    rec.log_static(
        "world/velocity",
        &rerun::Arrows3D::update_fields().with_colors([colour(COMMAND_RGB), colour(MEASURED_RGB)]),
    )?;
    if !probe.taus().is_empty() {
        rec.log_static(
            "value/quantiles",
            &rerun::BarChart::update_fields()
                .with_abscissa(rerun::datatypes::TensorData::from(probe.taus().to_vec()))
                // Bars sit at tau in (0, 1): without widths rerun draws each one
                // 1 wide and the 32 bars pile into one block over [0, 2].
                .with_widths(bar_widths(probe.taus())),
        )?;
    }
    Ok(())
}

impl EpisodeLogger {
    /// Logs the static parts (coordinate frame, geoms, series styles, flat ground) and
    /// returns a logger for the per-step data. `probe` says which taus the quantile bar
    /// chart shows (none for a scalar critic) and names the distorted value.
    pub fn new(
        rec: RecordingStream,
        robot: &Robot,
        terrain: Option<Arc<dyn HeightGrid>>,
        probe: ValueProbe,
    ) -> Result<EpisodeLogger> {
        rec.log_static("world", &rerun::ViewCoordinates::RIGHT_HAND_Z_UP())?;
        let bodies = log_robot_geoms(&rec, robot)?;
        log_follow_frame(&rec, &body_path(robot, robot.layout.trunk_body))?;
        if terrain.is_none() {
            log_mesh(
                &rec,
                "world/ground",
                &convert::ground_quad([0.0, 0.0], GROUND_HALF_EXTENT_M),
            )?;
        }
        log_plot_styles(&rec, robot, &probe)?;
        let nb = bodies.len();
        let worker = Worker::spawn(
            rec.clone(),
            bodies.iter().map(|(_, p)| p.clone()).collect(),
            probe,
        )?;
        Ok(EpisodeLogger {
            rec,
            bodies,
            policy: None,
            worker,
            terrain,
            logged_chunks: HashSet::new(),
            extra_timeline: None,
            cols: Columns {
                body_pos: vec![Vec::new(); nb],
                body_quat: vec![Vec::new(); nb],
                ..Default::default()
            },
            flush_steps: DEFAULT_FLUSH_STEPS,
            steps_in_batch: 0,
            time_s: 0.0,
            step: 0,
            frames: 0,
            value_every: VALUE_EVERY_FRAMES,
            push_shown: false,
            prev_base_vel_world: [0.0; 3],
        })
    }

    pub fn recording(&self) -> &RecordingStream {
        &self.rec
    }

    /// Steps buffered before sending (1 = send every step, for live viewing).
    pub fn set_flush_steps(&mut self, n: usize) {
        self.flush_steps = n.max(1);
    }

    /// Reads and logs the critic every `n` frames (1 = every policy step).
    pub fn set_value_every_frames(&mut self, n: usize) {
        self.value_every = n.max(1);
    }

    /// Tags every following row with a constant sequence value (e.g. `iteration`).
    pub fn set_extra_timeline(&mut self, name: &'static str, value: i64) -> Result<()> {
        self.flush()?;
        self.extra_timeline = Some((name, value));
        Ok(())
    }

    /// Current simulated time (s) and policy step of the recording.
    pub fn clock(&self) -> (f64, i64) {
        (self.time_s, self.step)
    }

    /// Number of bodies logged per step.
    pub fn num_bodies(&self) -> usize {
        self.bodies.len()
    }

    fn set_event_time(&self) {
        self.rec.set_duration_secs("sim_time", self.time_s);
        self.rec.set_time_sequence("step", self.step);
        if let Some((name, v)) = &self.extra_timeline {
            self.rec.set_time_sequence(*name, *v);
        }
    }

    /// A `TextLog` line at the current time.
    pub fn event(&self, level: &str, text: impl Into<String>) -> Result<()> {
        self.set_event_time();
        self.rec.log(
            "events",
            &rerun::TextLog::new(text.into()).with_level(level),
        )?;
        Ok(())
    }

    /// Starts an episode: logs the first frame (`obs`: the first observation).
    pub fn begin_episode(
        &mut self,
        learner: &Learner,
        env: &Env,
        label: &str,
        obs: &[f32],
    ) -> Result<()> {
        self.prev_base_vel_world = base_vel_world(env.robot());
        let c = env.command();
        let d = env.draw;
        self.event(
            rerun::TextLogLevel::INFO,
            format!(
                "{label}: command vx {:.2} m/s, vy {:.2} m/s, yaw rate {:.2} rad/s; friction {}, added base mass {:.2} kg; terrain level {} type {}",
                c[0],
                c[1],
                c[2],
                d.friction.map_or("model".to_string(), |f| format!("{f:.2}")),
                d.added_base_mass_kg,
                env.terrain_level,
                env.terrain_type
            ),
        )?;
        self.flush()?;
        self.policy = Some(Arc::new(learner.actor_critic().clone()));
        self.record(env, obs, None)
    }

    /// Logs the frame after a policy step: `dt_s` later, the state the step produced
    /// and (for the critic) `obs`, the observation it returned.
    pub fn log_step(
        &mut self,
        env: &Env,
        result: &StepResult,
        obs: &[f32],
        dt_s: f64,
    ) -> Result<()> {
        self.time_s += dt_s;
        self.step += 1;
        self.record(env, obs, Some(result))
    }

    fn record(&mut self, env: &Env, obs: &[f32], result: Option<&StepResult>) -> Result<()> {
        let robot = env.robot();
        let base = robot.base_pos_m();
        self.ensure_terrain_near(base)?;
        if let Some(r) = result {
            self.log_events(env, r)?;
        }
        let c = &mut self.cols;
        c.time_s.push(self.time_s);
        c.step.push(self.step);
        let (xpos, xquat) = (robot.data().xpos(), robot.data().xquat());
        for (i, (b, _)) in self.bodies.iter().enumerate() {
            let p = xpos[*b];
            c.body_pos[i].push([p[0] as f32, p[1] as f32, p[2] as f32]);
            c.body_quat[i].push(convert::quat_wxyz_to_xyzw(xquat[*b]));
        }
        let s = env.state();
        let cmd = env.command();
        c.vx.extend([cmd[0], s.base_lin_vel_body_mps[0]]);
        c.vy.extend([cmd[1], s.base_lin_vel_body_mps[1]]);
        c.wz.extend([cmd[2], s.base_ang_vel_body_rad_s[2]]);
        c.torques.extend(s.torques_nm);
        c.contacts
            .extend((0..4).map(|i| i as f64 + 0.8 * s.foot_contact[i] as u8 as f64));
        let crossed = result.map_or([false; NUM_RISK_TERMS], |r| r.risk.exceeded);
        c.risk_crossed
            .extend((0..NUM_RISK_TERMS).map(|k| k as f64 + 0.8 * crossed[k] as u8 as f64));
        // Command and measured planar velocity as world-frame arrows above the trunk.
        let yaw = roll_pitch_yaw(robot.base_quat_wxyz())[2];
        let heading = nalgebra::Rotation3::from_axis_angle(&nalgebra::Vector3::z_axis(), yaw);
        let cmd_world: [f64; 3] = (heading * nalgebra::Vector3::new(cmd[0], cmd[1], 0.0)).into();
        let v = base_vel_world(robot);
        let origin = [base[0] as f32, base[1] as f32, (base[2] + 0.15) as f32];
        c.arrows_origin.extend([origin, origin]);
        c.arrows_vec
            .extend([f32x3(cmd_world), [v[0] as f32, v[1] as f32, 0.0]]);
        if self.frames.is_multiple_of(self.value_every) {
            c.obs.extend_from_slice(obs);
            c.value_time_s.push(self.time_s);
            c.value_step.push(self.step);
        }
        self.frames += 1;
        // Batches hold `flush_steps` policy steps; an episode's first frame (its
        // reset state) rides with its first steps, so a 1000-step episode makes
        // 4 batches of 250 rather than 4 and a 1-frame remainder at the end.
        self.steps_in_batch += result.is_some() as usize;
        if self.steps_in_batch >= self.flush_steps {
            self.flush()?;
        }
        Ok(())
    }

    fn log_events(&mut self, env: &Env, r: &StepResult) -> Result<()> {
        for (k, (name, term)) in env.config().risk.terms().into_iter().enumerate() {
            // crossings are the `plots/risk_crossed` series; only fired penalties are events
            if r.risk.fired[k] {
                self.event(
                    rerun::TextLogLevel::ERROR,
                    format!("risk penalty: {name} (-{:.1})", term.weight),
                )?;
            }
        }
        let robot = env.robot();
        let base = robot.base_pos_m();
        let v = base_vel_world(robot);
        let fp = env.force_push();
        let push_vec: Option<[f32; 3]> = match env.config().randomization.push {
            PushConfig::VelocityKick { .. } if r.pushed => {
                // The kick is applied before the step: the velocity change over the
                // step shows it (plus one step of dynamics).
                Some([
                    (v[0] - self.prev_base_vel_world[0]) as f32,
                    (v[1] - self.prev_base_vel_world[1]) as f32,
                    0.0,
                ])
            }
            PushConfig::Force { .. } if r.pushed || fp.steps_left > 0 => {
                Some(fp.force_n.map(|f| f as f32 * PUSH_ARROW_M_PER_N))
            }
            _ => None,
        };
        self.prev_base_vel_world = v;
        if r.pushed {
            let what = match env.config().randomization.push {
                PushConfig::Force { .. } => {
                    format!(
                        "push: force [{:.0}, {:.0}, {:.0}] N on the trunk",
                        fp.force_n[0], fp.force_n[1], fp.force_n[2]
                    )
                }
                _ => {
                    let d = push_vec.unwrap_or_default();
                    format!("push: base velocity kick ~[{:.2}, {:.2}] m/s", d[0], d[1])
                }
            };
            self.event(rerun::TextLogLevel::INFO, what)?;
        }
        match push_vec {
            Some(vec) => {
                self.set_event_time();
                let origin = [base[0] as f32, base[1] as f32, base[2] as f32];
                let tail = [origin[0] - vec[0], origin[1] - vec[1], origin[2] - vec[2]];
                self.rec.log(
                    "world/push",
                    &rerun::Arrows3D::from_vectors([vec])
                        .with_origins([tail])
                        .with_colors([rerun::Color::from_rgb(230, 40, 40)]),
                )?;
                self.push_shown = true;
            }
            None if self.push_shown => {
                self.set_event_time();
                self.rec
                    .log("world/push", &rerun::archetypes::Clear::flat())?;
                self.push_shown = false;
            }
            None => {}
        }
        if r.done {
            self.event(
                rerun::TextLogLevel::INFO,
                format!(
                    "episode ended ({})",
                    if r.time_out { "time-out" } else { "fall" }
                ),
            )?;
        }
        Ok(())
    }

    /// Logs the terrain chunks within [`TERRAIN_RADIUS_M`] of `p` not logged yet.
    fn ensure_terrain_near(&mut self, p: [f64; 3]) -> Result<()> {
        let Some(t) = self.terrain.clone() else {
            return Ok(());
        };
        let (nx, ny) = t.grid_shape();
        let h = t.horizontal_scale_m();
        let [x0, y0] = t.grid_origin_m();
        let chunk_m = TERRAIN_CHUNK_SAMPLES as f64 * h;
        let (ncx, ncy) = (
            convert::chunk_count(TERRAIN_CHUNK_SAMPLES, nx),
            convert::chunk_count(TERRAIN_CHUNK_SAMPLES, ny),
        );
        let range = |c: f64, n: usize| {
            let lo = ((c - TERRAIN_RADIUS_M) / chunk_m).floor().max(0.0) as usize;
            let hi = (((c + TERRAIN_RADIUS_M) / chunk_m).floor().max(0.0) as usize).min(n - 1);
            lo..=hi
        };
        for cy in range(p[1] - y0, ncy) {
            for cx in range(p[0] - x0, ncx) {
                if !self.logged_chunks.insert((cx, cy)) {
                    continue;
                }
                let mesh = convert::heightfield_mesh(
                    t.heights_m(),
                    nx,
                    [x0, y0],
                    h,
                    convert::chunk_sample_range(cx, TERRAIN_CHUNK_SAMPLES, nx),
                    convert::chunk_sample_range(cy, TERRAIN_CHUNK_SAMPLES, ny),
                    t.height_range_m(),
                );
                log_mesh(&self.rec, &format!("world/terrain/chunk_{cx}_{cy}"), &mesh)?;
            }
        }
        Ok(())
    }

    /// Hands the buffered steps to the worker (critic + columns); returns at once
    /// unless two batches are already waiting.
    pub fn flush(&mut self) -> Result<()> {
        if self.cols.is_empty() {
            return Ok(());
        }
        let mut cols = std::mem::take(&mut self.cols);
        self.cols.reset(self.bodies.len());
        self.steps_in_batch = 0;
        cols.extra_timeline = self.extra_timeline;
        let ac = self
            .policy
            .clone()
            .context("the logger has no policy: call begin_episode first")?;
        if self.worker.tx.send(Job { cols, ac }).is_err() {
            // The worker stopped on an error: report it.
            return self.join_worker();
        }
        Ok(())
    }

    fn join_worker(&mut self) -> Result<()> {
        let (tx, _) = mpsc::sync_channel(1);
        drop(std::mem::replace(&mut self.worker.tx, tx));
        match self.worker.handle.take() {
            Some(h) => h
                .join()
                .map_err(|_| anyhow::anyhow!("the rerun logging thread panicked"))?,
            None => Ok(()),
        }
    }

    /// Flushes, waits for the worker and hands back the recording (to log more, or to close it).
    pub fn finish(mut self) -> Result<RecordingStream> {
        self.flush()?;
        self.join_worker()?;
        Ok(self.rec.clone())
    }
}

impl Drop for EpisodeLogger {
    fn drop(&mut self) {
        let _ = self.join_worker();
    }
}

/// A batch of frames for the worker, with the policy that produced them.
struct Job {
    cols: Columns,
    ac: Arc<ActorCritic>,
}

struct Worker {
    tx: mpsc::SyncSender<Job>,
    handle: Option<std::thread::JoinHandle<Result<()>>>,
}

impl Worker {
    /// The thread that reads the critic and sends the columns, so the simulation
    /// goes on meanwhile (jobs are handled in order).
    fn spawn(rec: RecordingStream, bodies: Vec<String>, probe: ValueProbe) -> Result<Worker> {
        let (tx, rx) = mpsc::sync_channel::<Job>(2);
        let handle = std::thread::Builder::new()
            .name("rall-viz".into())
            .spawn(move || -> Result<()> {
                // The critic's matmuls stay on this thread: on rayon's pool they
                // would take the simulation's core.
                crate::learn::mat::serial(|| {
                    // The static rows just logged (geometry, series styles) would wait in
                    // rerun's batcher for its next tick, which a short episode never
                    // reaches: have them encoded now, beside the simulation, rather than
                    // when the recording closes.
                    rec.flush_async().context("flushing the static scene")?;
                    for job in rx {
                        send_batch(&rec, &bodies, &probe, &job.ac, job.cols)?;
                    }
                    Ok(())
                })
            })
            .context("starting the logging thread")?;
        Ok(Worker {
            tx,
            handle: Some(handle),
        })
    }
}

/// Reads the critic for a batch of frames and sends every per-step entity as columns.
fn send_batch(
    rec: &RecordingStream,
    bodies: &[String],
    probe: &ValueProbe,
    ac: &ActorCritic,
    c: Columns,
) -> Result<()> {
    let n = c.len();
    let mut index = vec![
        TimeColumn::new_duration_secs("sim_time", c.time_s),
        TimeColumn::new_sequence("step", c.step),
    ];
    if let Some((name, v)) = c.extra_timeline {
        index.push(TimeColumn::new_sequence(name, std::iter::repeat_n(v, n)));
    }
    // The critic, once for the whole batch of its frames.
    let readings = probe.read_batch_ac(ac, &c.obs);
    let nv = readings.len();
    let mut value_index = vec![
        TimeColumn::new_duration_secs("sim_time", c.value_time_s),
        TimeColumn::new_sequence("step", c.value_step),
    ];
    if let Some((name, v)) = c.extra_timeline {
        value_index.push(TimeColumn::new_sequence(name, std::iter::repeat_n(v, nv)));
    }
    let stats: Vec<f64> = readings
        .iter()
        .flat_map(|r| [r.mean as f64, r.distorted as f64])
        .collect();
    let iqr: Vec<f64> = readings.iter().map(|r| r.iqr as f64).collect();
    let send = |path: &str, cols: Vec<rerun::SerializedComponentColumn>| -> Result<()> {
        rec.send_columns(path, index.clone(), cols)
            .with_context(|| format!("logging {path}"))?;
        Ok(())
    };
    for (i, path) in bodies.iter().enumerate() {
        send(
            path,
            rerun::Transform3D::update_fields()
                .with_many_translation(c.body_pos[i].iter().copied())
                .with_many_quaternion(
                    c.body_quat[i]
                        .iter()
                        .map(|q| rerun::Quaternion::from_xyzw(*q)),
                )
                .columns_of_unit_batches()?
                .collect(),
        )?;
    }
    let scalars = |vals: &[f64], k: usize| -> Result<Vec<rerun::SerializedComponentColumn>> {
        Ok(rerun::Scalars::new(vals.iter().copied())
            .columns(std::iter::repeat_n(k, vals.len() / k))?
            .collect())
    };
    send("plots/velocity/vx", scalars(&c.vx, 2)?)?;
    send("plots/velocity/vy", scalars(&c.vy, 2)?)?;
    send("plots/velocity/yaw_rate", scalars(&c.wz, 2)?)?;
    send("plots/torques", scalars(&c.torques, c.torques.len() / n)?)?;
    send("plots/contacts", scalars(&c.contacts, 4)?)?;
    send(
        "plots/risk_crossed",
        scalars(&c.risk_crossed, NUM_RISK_TERMS)?,
    )?;
    let send_value = |path: &str, cols: Vec<rerun::SerializedComponentColumn>| -> Result<()> {
        if nv > 0 {
            rec.send_columns(path, value_index.clone(), cols)
                .with_context(|| format!("logging {path}"))?;
        }
        Ok(())
    };
    send_value("value/stats", scalars(&stats, 2)?)?;
    send_value("value/iqr", scalars(&iqr, 1)?)?;
    send(
        "world/velocity",
        rerun::Arrows3D::update_fields()
            .with_vectors(c.arrows_vec.iter().copied())
            .with_origins(c.arrows_origin.iter().copied())
            .columns(std::iter::repeat_n(2, n))?
            .collect(),
    )?;
    if !probe.taus().is_empty() {
        send_value(
            "value/quantiles",
            rerun::BarChart::update_fields()
                .with_many_values(
                    readings
                        .into_iter()
                        .map(|r| rerun::datatypes::TensorData::from(centred(&r.quantiles, r.mean))),
                )
                .columns_of_unit_batches()?
                .collect(),
        )?;
    }
    Ok(())
}

/// `Z_tau(s) - mean`: rerun's bar chart always starts its bars at 0, so bars of
/// `Z_tau(s)` itself would show the value's level, not the distribution's shape.
pub fn centred(quantiles: &[f32], mean: f32) -> Vec<f32> {
    quantiles.iter().map(|q| q - mean).collect()
}

/// Width of each bar of the quantile chart: the spacing of its tau grid (`1 / n`
/// on the midpoint grid), so the bars tile [0, 1] side by side.
pub fn bar_widths(taus: &[f32]) -> Vec<f32> {
    let n = taus.len();
    (0..n)
        .map(|i| {
            let lo = if i == 0 {
                0.0
            } else {
                0.5 * (taus[i - 1] + taus[i])
            };
            let hi = if i + 1 == n {
                1.0
            } else {
                0.5 * (taus[i] + taus[i + 1])
            };
            (hi - lo).max(0.0)
        })
        .collect()
}

fn f32x3(v: [f64; 3]) -> [f32; 3] {
    [v[0] as f32, v[1] as f32, v[2] as f32]
}

/// World-frame linear velocity of the trunk (free joint qvel).
fn base_vel_world(robot: &Robot) -> [f64; 3] {
    let a = robot.layout.root_dof_adr;
    let q = robot.data().qvel();
    [q[a], q[a + 1], q[a + 2]]
}

/// Logs one primitive as static data at `path` (in its parent's frame).
pub fn log_primitive(
    rec: &RecordingStream,
    path: &str,
    prim: &Primitive,
    color: rerun::Color,
) -> Result<()> {
    let q = |x: [f32; 4]| rerun::Quaternion::from_xyzw(x);
    match *prim {
        Primitive::Box(b) => rec.log_static(
            path,
            &rerun::Boxes3D::from_centers_and_half_sizes([b.center], [b.half_size])
                .with_quaternions([q(b.quat_xyzw)])
                .with_colors([color])
                .with_fill_mode(rerun::FillMode::Solid),
        )?,
        Primitive::Capsule(cp) => rec.log_static(
            path,
            &rerun::Capsules3D::from_lengths_and_radii([cp.length], [cp.radius])
                .with_translations([cp.translation])
                .with_quaternions([q(cp.quat_xyzw)])
                .with_colors([color])
                .with_fill_mode(rerun::FillMode::Solid),
        )?,
        Primitive::Ellipsoid(e) => rec.log_static(
            path,
            &rerun::Ellipsoids3D::from_centers_and_half_sizes([e.center], [e.half_size])
                .with_quaternions([q(e.quat_xyzw)])
                .with_colors([color])
                .with_fill_mode(rerun::FillMode::Solid),
        )?,
        Primitive::Cylinder(cy) => rec.log_static(
            path,
            &rerun::Cylinders3D::from_lengths_and_radii([cy.length], [cy.radius])
                .with_centers([cy.center])
                .with_quaternions([q(cy.quat_xyzw)])
                .with_colors([color])
                .with_fill_mode(rerun::FillMode::Solid),
        )?,
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::{Data, Model};

    /// Every geom drawn under its carrier body, posed by that body's world transform,
    /// lands where MuJoCo puts it, with the legs bent away from the keyframe.
    #[test]
    fn geoms_of_welded_bodies_are_drawn_where_mujoco_puts_them() {
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
        let m = Model::from_xml_path(root.join("mjcf/aliengo.xml")).unwrap();
        let mut d = Data::new(&m).unwrap();
        d.reset_to_keyframe(&m, "stand").unwrap();
        for (i, q) in d.qpos_mut().iter_mut().enumerate().skip(7) {
            *q += 0.3 * ((i as f64) * 1.7).sin();
        }
        d.forward(&m).unwrap();
        let mut welded = 0;
        for g in 0..m.ngeom() {
            let (b, in_carrier) = carrier(&m, m.geom_body(g));
            if b == 0 {
                continue;
            }
            welded += (b != m.geom_body(g)) as usize;
            let geom = in_carrier.then(Pose {
                pos: m.geom_pos()[g],
                quat: m.geom_quat()[g],
            });
            let world = Pose {
                pos: d.xpos()[b],
                quat: d.xquat()[b],
            };
            let p = world.then(geom).pos;
            for k in 0..3 {
                assert!(
                    (p[k] - d.geom_xpos()[g][k]).abs() < 1e-9,
                    "geom {g}: {p:?} vs {:?}",
                    d.geom_xpos()[g]
                );
            }
        }
        assert_eq!(welded, 4, "the four feet are welded to their calves");
    }
}
