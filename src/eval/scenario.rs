//! The robustness scenarios of the paper's experiments (section V): payloads
//! (ball, frozen arm, moving arm), 100 N pushes, flat or random rough ground, a
//! platform drop and the race course, selectable by name.
//!
//! A scenario is an [`EnvConfig`] (the checkpoint's, with the scenario's pushes,
//! commands and episode length), its own MuJoCo model (robot + payload + ground,
//! with a keyframe extended to the payload's joints and holding the spawn pose),
//! and a per-env [`ScenarioHook`] for what the env does not know (the moving
//! arm's targets, payload-on-ground falls). Envs get no `Terrain`: the ground is
//! in the model and the spawn point in the keyframe.
//!
//! Names (combine with `+`, e.g. `ball+rough+push`):
//! - loads: `ball`, `frozen_arm`, `moving_arm` (default: none);
//! - ground: `flat` (default), `rough`, `platform` (0.40 m) or `platform=H`, `race`;
//! - `push`: 100 N on the trunk along a random +-x / +-y, every 300 steps for 50
//!   (always on in `race`).

use std::sync::Arc;

use anyhow::{bail, Context, Result};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;

use super::ground::{plane_xml, platform_xml, Ground, RaceTrackParams, RoughParams};
use super::mjcf::{self, JointValues, SceneParts};
use crate::env::config::PushConfig;
use crate::env::state::rotate;
use crate::env::terrain::TerrainKind;
use crate::env::{Env, EnvConfig, VecEnv};
use crate::robot::{Part, RobotLayout};
use crate::sim::{Data, JointKind, Model, ObjKind};
use nalgebra::Quaternion;

/// What the robot carries.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Load {
    None,
    /// A 2 kg ball rolling in an open 0.1 kg container on the trunk.
    Ball,
    /// The Z1 arm, joints held at the home pose.
    FrozenArm,
    /// The Z1 arm tracking random joint targets, re-sampled every few seconds.
    MovingArm,
}

impl Load {
    pub const PAYLOADS: [Load; 3] = [Load::Ball, Load::FrozenArm, Load::MovingArm];

    pub fn name(self) -> &'static str {
        match self {
            Load::None => "none",
            Load::Ball => "ball",
            Load::FrozenArm => "frozen_arm",
            Load::MovingArm => "moving_arm",
        }
    }
    /// The row label of the paper's table.
    pub fn label(self) -> &'static str {
        match self {
            Load::None => "None",
            Load::Ball => "Ball",
            Load::FrozenArm => "Frozen arm",
            Load::MovingArm => "Moving arm",
        }
    }
    fn has_arm(self) -> bool {
        matches!(self, Load::FrozenArm | Load::MovingArm)
    }
}

/// The ground under the robot.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
#[serde(rename_all = "snake_case", tag = "kind")]
pub enum GroundKind {
    Flat,
    /// Random rough ground (the paper's "Random" terrain).
    Rough,
    /// The robot starts on a platform of this height and walks off its edge.
    Platform {
        height_m: f64,
    },
    /// The race course (platform drop, obstacles, rough patches).
    RaceTrack,
}

impl GroundKind {
    pub fn name(&self) -> String {
        match self {
            GroundKind::Flat => "flat".into(),
            GroundKind::Rough => "rough".into(),
            GroundKind::Platform { height_m } => format!("platform={height_m:.2}"),
            GroundKind::RaceTrack => "race".into(),
        }
    }
}

/// A scenario: load x ground x pushes.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct ScenarioSpec {
    pub load: Load,
    pub ground: GroundKind,
    pub push: bool,
}

/// The words [`ScenarioSpec::parse`] knows.
pub const SCENARIO_WORDS: &[&str] = &[
    "ball",
    "frozen_arm",
    "moving_arm",
    "push",
    "flat",
    "rough",
    "platform",
    "platform=H",
    "race",
];

impl ScenarioSpec {
    pub fn new(load: Load, ground: GroundKind, push: bool) -> ScenarioSpec {
        ScenarioSpec { load, ground, push }
    }

    /// Parses `word+word+...` (see the module docs), e.g. `moving_arm+rough+push`,
    /// `platform=0.45`, `race`.
    pub fn parse(name: &str) -> Result<ScenarioSpec> {
        let mut spec = ScenarioSpec::new(Load::None, GroundKind::Flat, false);
        let (mut load_set, mut ground_set) = (false, false);
        for word in name.split('+').map(str::trim) {
            let (load, ground) = match word {
                "ball" => (Some(Load::Ball), None),
                "frozen_arm" | "frozen-arm" | "arm" => (Some(Load::FrozenArm), None),
                "moving_arm" | "moving-arm" => (Some(Load::MovingArm), None),
                "push" | "pushes" => {
                    spec.push = true;
                    (None, None)
                }
                "flat" => (None, Some(GroundKind::Flat)),
                "rough" | "random" => (None, Some(GroundKind::Rough)),
                "platform" => (None, Some(GroundKind::Platform { height_m: 0.40 })),
                "race" | "race_track" => (None, Some(GroundKind::RaceTrack)),
                w if w.starts_with("platform=") => {
                    let h: f64 = w["platform=".len()..].parse().with_context(|| {
                        format!("scenario {name:?}: {w:?} needs a height in metres")
                    })?;
                    if !(h.is_finite() && h > 0.0 && h < 2.0) {
                        bail!("scenario {name:?}: platform height {h} m is not in (0, 2)");
                    }
                    (None, Some(GroundKind::Platform { height_m: h }))
                }
                w => bail!(
                    "scenario {name:?}: unknown word {w:?} (known: {})",
                    SCENARIO_WORDS.join(", ")
                ),
            };
            if let Some(l) = load {
                if load_set {
                    bail!("scenario {name:?}: more than one load");
                }
                spec.load = l;
                load_set = true;
            }
            if let Some(g) = ground {
                if ground_set {
                    bail!("scenario {name:?}: more than one ground");
                }
                spec.ground = g;
                ground_set = true;
            }
        }
        if spec.ground == GroundKind::RaceTrack {
            spec.push = true;
        }
        Ok(spec)
    }

    /// The canonical name (parses back to the same spec).
    pub fn name(&self) -> String {
        let mut words = Vec::new();
        if self.load != Load::None {
            words.push(self.load.name().to_string());
        }
        words.push(self.ground.name());
        if self.push && self.ground != GroundKind::RaceTrack {
            words.push("push".into());
        }
        words.join("+")
    }
}

/// Where the platform is (platform scenarios).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct PlatformGeometry {
    pub height_m: f64,
    /// x of the edge the robot walks off (it walks along +x).
    pub edge_x_m: f64,
}

/// Platform scene settings.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PlatformParams {
    /// Trunk spawn distance before the edge, m.
    pub spawn_before_edge_m: f64,
    pub length_m: f64,
    pub width_m: f64,
}

impl Default for PlatformParams {
    fn default() -> Self {
        PlatformParams {
            spawn_before_edge_m: 0.8,
            length_m: 6.0,
            width_m: 8.0,
        }
    }
}

/// Everything tunable about the scenarios; defaults follow the paper where it says.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ScenarioParams {
    /// Episode length (s); `None`: the checkpoint's on flat/rough ground, 8 s on a
    /// platform, 30 s on the race course.
    pub episode_length_s: Option<f64>,
    /// Fixed command (vx m/s, vy m/s, yaw rate rad/s); `None`: the checkpoint's
    /// random commands on flat/rough ground. Platform and race use `forward_mps`.
    pub command: Option<[f64; 3]>,
    /// Forward speed command on the platform and the race course (m/s).
    pub forward_mps: f64,
    /// Evaluation pushes (paper: 100 N every 300 steps for 50 steps).
    pub push_force_n: f64,
    pub push_every_steps: usize,
    pub push_hold_steps: usize,
    /// Friction and added base mass ranges (paper table III), the same for every
    /// policy; `None` keeps the model's.
    pub friction: Option<[f64; 2]>,
    pub added_base_mass_kg: Option<[f64; 2]>,
    /// Moving arm: new random joint targets every this many seconds.
    pub arm_resample_s: f64,
    /// Arm pose of the keyframe and of the frozen arm (menagerie's "home"), rad.
    pub arm_home_rad: [f64; 6],
    /// The ball container's inner length and width, as a factor of 0.34 x 0.18 m.
    #[serde(skip_serializing_if = "is_one")]
    pub ball_container_scale: f64,
    pub rough: RoughParams,
    pub platform: PlatformParams,
    pub race: RaceTrackParams,
}

impl Default for ScenarioParams {
    fn default() -> Self {
        ScenarioParams {
            episode_length_s: None,
            command: None,
            forward_mps: 0.6,
            push_force_n: 100.0,
            push_every_steps: 300,
            push_hold_steps: 50,
            friction: Some([0.5, 1.5]),
            added_base_mass_kg: Some([-0.5, 1.0]),
            arm_resample_s: 2.0,
            arm_home_rad: [0.0, 0.785, -0.261, -0.523, 0.0, 0.0],
            ball_container_scale: 1.0,
            rough: RoughParams::default(),
            platform: PlatformParams::default(),
            race: RaceTrackParams::default(),
        }
    }
}

fn is_one(x: &f64) -> bool {
    *x == 1.0
}

/// The ball container's trunk fragment with its inner length and width times
/// `scale` (walls 6 mm thick, 0.08 m high, mass 0.1 kg); at 1 the MJCF file's own.
fn ball_container_trunk_xml(scale: f64) -> Result<String> {
    let original = mjcf::fragment(mjcf::BALL_CONTAINER_XML, "trunk")?;
    if scale == 1.0 {
        return Ok(original.to_string());
    }
    let (lx, ly) = (0.17 * scale, 0.09 * scale); // inner half sides
    let (bx, by) = (lx + 0.006, ly + 0.006);
    let wall = |name: &str, size: [f64; 3], pos: [f64; 3]| {
        format!(
            "      <geom name=\"container_{name}\" type=\"box\" size=\"{} {} {}\" pos=\"{} {} {}\" contype=\"3\" conaffinity=\"0\" rgba=\"0.2 0.45 0.8 0.6\"/>\n",
            size[0], size[1], size[2], pos[0], pos[1], pos[2]
        )
    };
    let s2 = scale * scale;
    let mut xml = format!(
        "\n    <body name=\"payload_container\" pos=\"0 0 0.056\">\n      <inertial pos=\"0 0 0.03\" mass=\"0.1\" diaginertia=\"{} {} {}\"/>\n",
        0.0006 * s2,
        0.0013 * s2,
        0.0017 * s2
    );
    xml += &wall("bottom", [bx, by, 0.003], [0.0, 0.0, 0.003]);
    xml += &wall("front", [0.003, by, 0.04], [lx + 0.003, 0.0, 0.046]);
    xml += &wall("back", [0.003, by, 0.04], [-(lx + 0.003), 0.0, 0.046]);
    xml += &wall("left", [bx, 0.003, 0.04], [0.0, ly + 0.003, 0.046]);
    xml += &wall("right", [bx, 0.003, 0.04], [0.0, -(ly + 0.003), 0.046]);
    xml += "    </body>\n    ";
    Ok(xml)
}

/// Z1 joint names in chain order.
pub const ARM_JOINTS: [&str; 6] = [
    "z1_joint1",
    "z1_joint2",
    "z1_joint3",
    "z1_joint4",
    "z1_joint5",
    "z1_joint6",
];

/// Geoms fixed to the trunk whose touching the ground counts as a fall: the
/// container, and the arm's base, shoulder and upper arm (which cannot reach the
/// ground while the trunk is upright; the forearm and wrist can).
const FALL_GEOM_PREFIXES: [&str; 5] = [
    "container_",
    "z1_base",
    "z1_shoulder",
    "z1_upper_arm",
    "z1_elbow",
];

/// A built scenario: config, model and what its hooks need.
pub struct ScenarioSetup {
    pub spec: ScenarioSpec,
    pub params: ScenarioParams,
    /// The env config to run (the base config with the scenario's changes).
    pub env: EnvConfig,
    /// Robot + payload + ground; its keyframe `env.control.default_keyframe` holds
    /// the spawn pose and the payload's initial state.
    pub model: Arc<Model>,
    /// The heightfield (rough ground and race course), for drawing.
    pub ground: Option<Arc<Ground>>,
    /// Trunk position of the keyframe (m).
    pub spawn_m: [f64; 3],
    pub platform: Option<PlatformGeometry>,
    hook: HookTemplate,
}

/// Shared, immutable part of every env's hook.
#[derive(Debug, Clone)]
struct HookTemplate {
    /// Arm actuators and joint ranges (arm loads).
    arm: Option<Arc<ArmInfo>>,
    moving: bool,
    resample_steps: usize,
    /// Per geom id: touching the world body is a fall.
    fall_geoms: Arc<Vec<bool>>,
    /// Per geom id: touching the world body is a fall under the strict definition
    /// (any geom of the robot or fixed to it but the feet: hips, thighs, calves,
    /// trunk, container, the whole arm).
    strict_fall_geoms: Arc<Vec<bool>>,
}

#[derive(Debug, Clone)]
struct ArmInfo {
    actuators: [usize; 6],
    ranges: [[f64; 2]; 6],
    home: [f64; 6],
}

/// Per-env scenario logic, called around the env's own reset and step:
/// [`ScenarioHook::on_reset`] after every reset, [`ScenarioHook::before_step`]
/// before every step, [`ScenarioHook::payload_on_ground`] after a step.
#[derive(Debug, Clone)]
pub struct ScenarioHook {
    t: HookTemplate,
    rng: ChaCha8Rng,
    /// Current arm targets (rad).
    pub arm_targets: [f64; 6],
    /// Arm targets re-sampled since creation.
    pub arm_resamples: u64,
}

impl ScenarioHook {
    /// After `env.reset`: the arm's servo targets back to the home pose.
    pub fn on_reset(&mut self, env: &mut Env) {
        if let Some(arm) = &self.t.arm {
            self.arm_targets = arm.home;
            write_arm_targets(env, arm, &self.arm_targets);
        }
    }

    /// Before `env.step`: the moving arm draws new targets every few seconds.
    pub fn before_step(&mut self, env: &mut Env) {
        let Some(arm) = self.t.arm.clone() else {
            return;
        };
        let s = env.step_in_episode();
        if self.t.moving && s > 0 && s.is_multiple_of(self.t.resample_steps) {
            for (t, r) in self.arm_targets.iter_mut().zip(&arm.ranges) {
                *t = self.rng.gen_range(r[0]..=r[1]);
            }
            self.arm_resamples += 1;
            write_arm_targets(env, &arm, &self.arm_targets);
        }
    }

    /// Whether a payload part fixed to the trunk (container, arm base or upper
    /// arm) touches the ground: the robot has fallen even if the env goes on.
    pub fn payload_on_ground(&self, env: &Env) -> bool {
        touches_ground(env, &self.t.fall_geoms)
    }

    /// Whether any part of the robot but its feet, or of what is fixed to it,
    /// touches the ground (the strict fall definition).
    pub fn non_foot_on_ground(&self, env: &Env) -> bool {
        touches_ground(env, &self.t.strict_fall_geoms)
    }
}

/// Whether a geom marked in `mask` touches a geom of the world body.
fn touches_ground(env: &Env, mask: &[bool]) -> bool {
    let r = env.robot();
    r.data().contacts().any(|c| {
        (mask[c.geom1] && r.model().geom_body(c.geom2) == 0)
            || (mask[c.geom2] && r.model().geom_body(c.geom1) == 0)
    })
}

fn write_arm_targets(env: &mut Env, arm: &ArmInfo, targets: &[f64; 6]) {
    let ctrl = env.robot_mut().data_mut().ctrl_mut();
    for (a, t) in arm.actuators.iter().zip(targets) {
        ctrl[*a] = *t;
    }
}

impl ScenarioSetup {
    /// The hook of env `index` (its random stream depends on `seed` and `index`).
    pub fn hook(&self, index: usize, seed: u64) -> ScenarioHook {
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x5343_454e_4152_494f);
        rng.set_stream(index as u64);
        ScenarioHook {
            t: self.hook.clone(),
            rng,
            arm_targets: self.hook.arm.as_ref().map_or([0.0; 6], |a| a.home),
            arm_resamples: 0,
        }
    }

    /// `n` envs of this scenario on `threads` threads, reset, with their hooks applied.
    pub fn vec_env(
        &self,
        n: usize,
        threads: usize,
        seed: u64,
    ) -> Result<(VecEnv, Vec<ScenarioHook>)> {
        let mut venv = VecEnv::new(
            Arc::new(self.env.clone()),
            &self.model,
            None,
            n,
            threads,
            seed,
        )
        .with_context(|| format!("creating {n} envs of scenario {}", self.spec.name()))?;
        let mut hooks: Vec<ScenarioHook> = (0..n).map(|i| self.hook(i, seed)).collect();
        for (h, e) in hooks.iter_mut().zip(venv.envs_mut()) {
            h.on_reset(e);
        }
        Ok((venv, hooks))
    }

    /// One env of this scenario (the viewer), with its hook.
    pub fn single_env(&self, seed: u64) -> Result<(Env, ScenarioHook)> {
        let env = Env::new(Arc::new(self.env.clone()), &self.model, None, seed, 0)
            .with_context(|| format!("creating an env of scenario {}", self.spec.name()))?;
        Ok((env, self.hook(0, seed)))
    }

    /// Total mass of the scene's bodies (kg): robot + payload.
    pub fn total_mass_kg(&self) -> f64 {
        self.model.total_mass_kg()
    }
}

/// The env config of a scenario: `base` (noise, PD, rewards of the checkpoint)
/// with the scenario's pushes, commands, randomisation and episode length.
pub fn scenario_env_config(spec: &ScenarioSpec, base: &EnvConfig, p: &ScenarioParams) -> EnvConfig {
    let mut cfg = base.clone();
    cfg.terrain.kind = TerrainKind::Flat; // the ground is in the scenario's model
    cfg.episode.randomize_initial_length = false;
    cfg.randomization.friction = p.friction;
    cfg.randomization.added_base_mass_kg = p.added_base_mass_kg;
    cfg.randomization.push = if spec.push {
        PushConfig::Force {
            force_n: p.push_force_n,
            every_steps: p.push_every_steps,
            hold_steps: p.push_hold_steps,
        }
    } else {
        PushConfig::None
    };
    let fixed = match spec.ground {
        GroundKind::Platform { .. } | GroundKind::RaceTrack => Some([p.forward_mps, 0.0, 0.0]),
        _ => p.command,
    };
    if let Some([vx, vy, wz]) = fixed {
        cfg.commands.vx_mps = [vx, vx];
        cfg.commands.vy_mps = [vy, vy];
        cfg.commands.yaw_rate_rad_s = [wz, wz];
        cfg.commands.zero_below_mps = 0.0;
    }
    cfg.episode.length_s = match (p.episode_length_s, spec.ground) {
        (Some(s), _) => s,
        (None, GroundKind::Platform { .. }) => 8.0,
        (None, GroundKind::RaceTrack) => 30.0,
        (None, _) => base.episode.length_s,
    };
    cfg
}

/// Half side of the rough field: far enough for the fastest command over the
/// whole episode (plus 3 m), at least 5 m, at most `p.half_extent_m`.
fn rough_half_extent(cfg: &EnvConfig, p: &RoughParams) -> f64 {
    let c = &cfg.commands;
    let vx = c.vx_mps[0].abs().max(c.vx_mps[1].abs());
    let vy = c.vy_mps[0].abs().max(c.vy_mps[1].abs());
    (vx.hypot(vy) * cfg.episode.length_s + 3.0)
        .min(p.half_extent_m)
        .max(5.0)
}

/// Builds scenario `spec` on top of `base` (the checkpoint's env config).
/// `seed` generates the random ground.
pub fn build_scenario(
    spec: &ScenarioSpec,
    base: &EnvConfig,
    params: &ScenarioParams,
    seed: u64,
) -> Result<ScenarioSetup> {
    let env = scenario_env_config(spec, base, params);
    env.validate()
        .map_err(|e| anyhow::anyhow!("scenario {}: {e}", spec.name()))?;
    let (path, robot_xml) = env.read_robot_mjcf().map_err(|(path, reason)| {
        anyhow::anyhow!("reading the robot MJCF {}: {reason}", path.display())
    })?;
    let robot = Model::from_xml_str(&robot_xml, &path.display().to_string())?;
    let key_name = env.control.default_keyframe.clone();
    let robot_key = mjcf::key_joint_values(&robot, &key_name)?;

    let mut parts = SceneParts::default();
    match spec.load {
        Load::None => {}
        Load::Ball => {
            parts.trunk = ball_container_trunk_xml(params.ball_container_scale)?;
            parts.world = mjcf::fragment(mjcf::BALL_CONTAINER_XML, "world")?.to_string();
        }
        Load::FrozenArm | Load::MovingArm => {
            parts.trunk = mjcf::fragment(mjcf::Z1_ARM_XML, "trunk")?.to_string();
            parts.actuator = mjcf::fragment(mjcf::Z1_ARM_XML, "actuator")?.to_string();
        }
    }
    let mut ground = None;
    let mut platform = None;
    let spawn: [f64; 3];
    let ground_world = match spec.ground {
        GroundKind::Flat => {
            spawn = [0.0, 0.0, 0.0];
            plane_xml()
        }
        GroundKind::Rough => {
            let mut rp = params.rough.clone();
            rp.half_extent_m = rough_half_extent(&env, &params.rough);
            let g = Ground::rough(&rp, seed);
            spawn = [0.0, 0.0, g.height_at(0.0, 0.0)];
            let (asset, world) = g.xml();
            parts.asset.push_str(&asset);
            ground = Some(Arc::new(g));
            world
        }
        GroundKind::Platform { height_m } => {
            let pp = &params.platform;
            let edge = pp.spawn_before_edge_m;
            spawn = [0.0, 0.0, height_m];
            platform = Some(PlatformGeometry {
                height_m,
                edge_x_m: edge,
            });
            format!(
                "{}\n{}",
                plane_xml(),
                platform_xml(height_m, edge, pp.length_m, pp.width_m)
            )
        }
        GroundKind::RaceTrack => {
            let g = Ground::race_track(&params.race, seed);
            spawn = [0.0, 0.0, g.height_at(0.0, 0.0)];
            let (asset, world) = g.xml();
            parts.asset.push_str(&asset);
            ground = Some(Arc::new(g));
            world
        }
    };
    parts.world = format!("{ground_world}\n{}", parts.world);

    // First pass without a keyframe: the scene's joints and their MJCF defaults.
    let label = format!("{} + scenario {}", path.display(), spec.name());
    let xml = mjcf::scene_xml(&robot_xml, &parts, None)?;
    let draft = Model::from_xml_str(&xml, &label)?;
    let mut d = Data::new(&draft)?;
    d.reset(&draft)?;
    let qpos0 = d.qpos().to_vec();
    let values = scene_key(&draft, &qpos0, &robot_key, spawn, spec.load, params)?;
    let key = mjcf::keyframe_xml(&draft, &key_name, &values)?;
    let xml = mjcf::scene_xml(&robot_xml, &parts, Some(&key))?;
    let mut model = Model::from_xml_str(&xml, &label)?;
    if let Some(g) = &ground {
        g.upload(&mut model).map_err(|e| anyhow::anyhow!(e))?;
    }
    let hook = hook_template(&model, &env, spec.load, params)?;
    let root = robot_key
        .iter()
        .find(|(_, v)| v.len() == 7)
        .map(|(_, v)| v.clone())
        .context("the robot keyframe has no free joint")?;
    Ok(ScenarioSetup {
        spec: *spec,
        params: params.clone(),
        env,
        model: Arc::new(model),
        ground,
        spawn_m: [root[0] + spawn[0], root[1] + spawn[1], root[2] + spawn[2]],
        platform,
        hook,
    })
}

/// Builds a scenario by name (see [`ScenarioSpec::parse`]) with default
/// parameters: the entry point of `rall play --scenario NAME`.
pub fn build_named_scenario(name: &str, base: &EnvConfig, seed: u64) -> Result<ScenarioSetup> {
    build_scenario(
        &ScenarioSpec::parse(name)?,
        base,
        &ScenarioParams::default(),
        seed,
    )
}

/// Hamilton product of (w, x, y, z) quaternions.
fn quat_mul(a: [f64; 4], b: [f64; 4]) -> [f64; 4] {
    let q = Quaternion::new(a[0], a[1], a[2], a[3]) * Quaternion::new(b[0], b[1], b[2], b[3]);
    [q.w, q.i, q.j, q.k]
}

/// The scene keyframe: the robot's key moved to `spawn`, free payload bodies at
/// their MJCF pose taken relative to the trunk, arm joints at home, other
/// joints at their MJCF default.
fn scene_key(
    scene: &Model,
    qpos0: &[f64],
    robot_key: &JointValues,
    spawn: [f64; 3],
    load: Load,
    p: &ScenarioParams,
) -> Result<JointValues> {
    let mut values: JointValues = Vec::new();
    let mut root_pose = None;
    for (name, v) in robot_key {
        let mut v = v.clone();
        if v.len() == 7 {
            for i in 0..3 {
                v[i] += spawn[i];
            }
            root_pose = Some(v.clone());
        }
        values.push((name.clone(), v));
    }
    let root = root_pose.context("the robot keyframe has no free joint")?;
    let (pos, quat) = (
        [root[0], root[1], root[2]],
        [root[3], root[4], root[5], root[6]],
    );
    for j in 0..scene.njnt() {
        let name = scene.name(ObjKind::Joint, j).to_string();
        if values.iter().any(|(n, _)| *n == name) {
            continue;
        }
        let a = scene.joint_qpos_adr(j);
        let v = match scene.joint_kind(j) {
            JointKind::Free => {
                let local = [qpos0[a], qpos0[a + 1], qpos0[a + 2]];
                let q0 = [qpos0[a + 3], qpos0[a + 4], qpos0[a + 5], qpos0[a + 6]];
                let w = rotate(quat, local);
                let q = quat_mul(quat, q0);
                vec![
                    pos[0] + w[0],
                    pos[1] + w[1],
                    pos[2] + w[2],
                    q[0],
                    q[1],
                    q[2],
                    q[3],
                ]
            }
            JointKind::Ball => qpos0[a..a + 4].to_vec(),
            _ => match ARM_JOINTS.iter().position(|n| *n == name) {
                Some(i) if load.has_arm() => vec![p.arm_home_rad[i]],
                _ => vec![qpos0[a]],
            },
        };
        values.push((name, v));
    }
    Ok(values)
}

fn hook_template(
    model: &Model,
    env: &EnvConfig,
    load: Load,
    p: &ScenarioParams,
) -> Result<HookTemplate> {
    let layout = RobotLayout::resolve(model)?;
    let fall_geoms = (0..model.ngeom())
        .map(|g| {
            let name = model.name(ObjKind::Geom, g);
            layout.geom_parts[g] == Part::Other
                && FALL_GEOM_PREFIXES.iter().any(|p| name.starts_with(p))
        })
        .collect();
    let arm = if load.has_arm() {
        let mut actuators = [0; 6];
        let mut ranges = [[0.0; 2]; 6];
        for (i, name) in ARM_JOINTS.iter().enumerate() {
            let j = model.require_id(ObjKind::Joint, name)?;
            actuators[i] = (0..model.nu())
                .find(|&a| model.actuator_joint(a) == Some(j))
                .with_context(|| format!("no actuator drives {name}"))?;
            ranges[i] = model
                .joint_range(j)
                .with_context(|| format!("arm joint {name} has no range"))?;
        }
        Some(Arc::new(ArmInfo {
            actuators,
            ranges,
            home: p.arm_home_rad,
        }))
    } else {
        None
    };
    let resample_steps = (p.arm_resample_s / env.control.policy_dt_s())
        .round()
        .max(1.0) as usize;
    Ok(HookTemplate {
        arm,
        moving: load == Load::MovingArm,
        resample_steps,
        fall_geoms: Arc::new(fall_geoms),
        strict_fall_geoms: Arc::new(strict_fall_geoms(model, &layout)),
    })
}

/// Geoms of the trunk's body tree (the robot and what is welded to it) that are
/// not feet.
fn strict_fall_geoms(model: &Model, layout: &RobotLayout) -> Vec<bool> {
    let on_robot = |mut b: usize| {
        while b != 0 {
            if b == layout.trunk_body {
                return true;
            }
            b = model.body_parent(b);
        }
        false
    };
    (0..model.ngeom())
        .map(|g| !matches!(layout.geom_parts[g], Part::Foot(_)) && on_robot(model.geom_body(g)))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_parse_and_round_trip() {
        let s = ScenarioSpec::parse("moving_arm+rough+push").unwrap();
        assert_eq!(
            s,
            ScenarioSpec::new(Load::MovingArm, GroundKind::Rough, true)
        );
        assert_eq!(ScenarioSpec::parse(&s.name()).unwrap(), s);
        let p = ScenarioSpec::parse("platform=0.45").unwrap();
        assert_eq!(p.ground, GroundKind::Platform { height_m: 0.45 });
        assert_eq!(ScenarioSpec::parse(&p.name()).unwrap(), p);
        assert!(ScenarioSpec::parse("race").unwrap().push);
        assert!(ScenarioSpec::parse("ball+frozen_arm").is_err());
        assert!(ScenarioSpec::parse("flat+rough").is_err());
        assert!(ScenarioSpec::parse("banana").is_err());
        assert!(ScenarioSpec::parse("platform=-1").is_err());
    }

    #[test]
    fn quaternion_product_of_identity() {
        let q = [0.5f64.sqrt(), 0.0, 0.0, 0.5f64.sqrt()];
        assert_eq!(quat_mul([1.0, 0.0, 0.0, 0.0], q), q);
    }
}
