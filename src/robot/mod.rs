//! The Aliengo on top of the simulation layer: layout, PD control, standing check.

mod layout;
mod params;
mod pd;
mod standing;

pub use layout::{Part, RobotLayout, LEGS, LEG_JOINTS, NUM_JOINTS};
pub use params::RobotParams;
pub use pd::ControlConfig;
pub use standing::{has_ground, standing_check, with_floor, StandingReport};

use std::cell::RefCell;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Weak};

use crate::sim::{Data, Model, ObjKind, Result, SimError};

/// Where a robot's model lives.
enum ModelSlot {
    /// Its own copy; `written` is the params token last written into it.
    Own { model: Model, written: u64 },
    /// A model shared with other robots (the terrain is stored once). Each
    /// thread that steps such robots keeps one working copy of it (see
    /// [`with_worker_model`]) and writes the stepping robot's [`RobotParams`]
    /// into it first, so per-robot randomisation costs no model copy per robot.
    Shared(Arc<Model>),
}

/// Source of params tokens: every robot's every params version gets its own.
static NEXT_TOKEN: AtomicU64 = AtomicU64::new(1);

fn fresh_token() -> u64 {
    NEXT_TOKEN.fetch_add(1, Ordering::Relaxed)
}

/// One simulated robot: model, state, layout and its PD controller.
///
/// The model and the state are private: the state can be read and edited but a
/// robot always steps its own state with its own model family and parameters.
pub struct Robot {
    model: ModelSlot,
    data: Data,
    /// The values this robot's model must hold when it steps.
    params: RobotParams,
    /// Identifies this robot's current `params` (see [`ModelSlot`]).
    token: u64,
    pub layout: RobotLayout,
    pub control: ControlConfig,
    /// Default joint angles (rad) from the control keyframe, SDK order.
    pub default_q_rad: [f64; NUM_JOINTS],
    /// Per-motor torque multiplier (domain randomisation; 1 = nominal), SDK order.
    pub motor_strength: [f64; NUM_JOINTS],
}

impl Robot {
    /// Wraps a loaded model as this robot's own copy: resolves the layout,
    /// applies the physics time step and resets to the default keyframe.
    pub fn new(model: Model, control: ControlConfig) -> Result<Robot> {
        Robot::build(ModelSlot::Own { model, written: 0 }, control)
    }

    /// A robot over a model shared with other robots (no copy of its own):
    /// randomisation goes into [`Robot::params_mut`] and is written into the
    /// stepping thread's working copy before each step.
    pub fn shared(model: Arc<Model>, control: ControlConfig) -> Result<Robot> {
        Robot::build(ModelSlot::Shared(model), control)
    }

    fn build(slot: ModelSlot, control: ControlConfig) -> Result<Robot> {
        control.validate().map_err(SimError::Invalid)?;
        let model = match &slot {
            ModelSlot::Own { model, .. } => model,
            ModelSlot::Shared(m) => m.as_ref(),
        };
        let layout = RobotLayout::resolve(model)?;
        let key = model.require_id(ObjKind::Key, &control.default_keyframe)?;
        let key_qpos = model.key_qpos(key);
        let default_q_rad = std::array::from_fn(|i| key_qpos[layout.qpos_adr[i]]);
        let mut params = RobotParams::of(model);
        params.set_timestep_s(control.physics_dt_s);
        let data = Data::new(model)?;
        let mut robot = Robot {
            model: slot,
            data,
            params,
            token: fresh_token(),
            layout,
            control,
            default_q_rad,
            motor_strength: [1.0; NUM_JOINTS],
        };
        robot.reset_to_default()?;
        Ok(robot)
    }

    /// Loads an MJCF file and wraps it.
    pub fn load(path: impl AsRef<std::path::Path>, control: ControlConfig) -> Result<Robot> {
        Robot::new(Model::from_xml_path(path)?, control)
    }

    /// The model, for names, sizes and geometry. Masses, friction and the time
    /// step it holds may not be this robot's: those are [`Robot::params`].
    pub fn model(&self) -> &Model {
        match &self.model {
            ModelSlot::Own { model, .. } => model,
            ModelSlot::Shared(m) => m,
        }
    }

    /// Whether the model is shared with other robots.
    pub fn shares_model(&self) -> bool {
        matches!(self.model, ModelSlot::Shared(_))
    }

    /// The state.
    pub fn data(&self) -> &Data {
        &self.data
    }

    /// The state, writable (positions, velocities, controls, applied forces).
    /// Call [`Robot::forward`] after editing positions.
    pub fn data_mut(&mut self) -> &mut Data {
        &mut self.data
    }

    /// The physical parameters this robot steps with.
    pub fn params(&self) -> &RobotParams {
        &self.params
    }

    /// Edits the physical parameters (written into the model before the next
    /// MuJoCo call of this robot).
    pub fn params_mut(&mut self) -> &mut RobotParams {
        self.token = fresh_token();
        &mut self.params
    }

    /// A model of its own holding this robot's parameters (what a per-robot
    /// model copy would be), e.g. for raw benchmarks and comparisons.
    pub fn model_copy(&self) -> Result<Model> {
        let mut m = self.model().try_clone()?;
        self.params.write_into(&mut m);
        Ok(m)
    }

    /// Restores a [`Data::physics_state`] of this robot's model family.
    pub fn set_physics_state(&mut self, state: &[f64]) -> Result<()> {
        let model = match &self.model {
            ModelSlot::Own { model, .. } => model,
            ModelSlot::Shared(m) => m.as_ref(),
        };
        self.data.set_physics_state(model, state)
    }

    /// Resets the state to the default keyframe.
    pub fn reset_to_default(&mut self) -> Result<()> {
        let key = self.control.default_keyframe.clone();
        run(
            &mut self.model,
            self.token,
            &self.params,
            &mut self.data,
            |m, d| d.reset_to_keyframe(m, &key),
        )
    }

    /// Recomputes derived quantities after the state was edited.
    pub fn forward(&mut self) -> Result<()> {
        run(
            &mut self.model,
            self.token,
            &self.params,
            &mut self.data,
            |m, d| d.forward(m),
        )
    }

    /// One physics step under PD towards `target_rad`; returns the applied torques (N m).
    #[inline]
    pub fn pd_substep(&mut self, target_rad: &[f64; NUM_JOINTS]) -> Result<[f64; NUM_JOINTS]> {
        let (layout, control, strength) = (&self.layout, &self.control, &self.motor_strength);
        run(
            &mut self.model,
            self.token,
            &self.params,
            &mut self.data,
            |m, d| pd_step(m, d, layout, control, strength, target_rad),
        )
    }

    /// One policy step: `decimation` PD physics steps towards the action's targets.
    pub fn policy_step(&mut self, action: &[f32]) -> Result<[f64; NUM_JOINTS]> {
        let target = self.control.joint_targets(&self.default_q_rad, action);
        let (layout, control, strength) = (&self.layout, &self.control, &self.motor_strength);
        run(
            &mut self.model,
            self.token,
            &self.params,
            &mut self.data,
            |m, d| {
                let mut tau = [0.0; NUM_JOINTS];
                for _ in 0..control.decimation {
                    tau = pd_step(m, d, layout, control, strength, &target)?;
                }
                Ok(tau)
            },
        )
    }

    /// Trunk position (world, m).
    pub fn base_pos_m(&self) -> [f64; 3] {
        let a = self.layout.root_qpos_adr;
        let q = self.data.qpos();
        [q[a], q[a + 1], q[a + 2]]
    }

    /// Trunk orientation (unit quaternion w x y z, world).
    pub fn base_quat_wxyz(&self) -> [f64; 4] {
        let a = self.layout.root_qpos_adr + 3;
        let q = self.data.qpos();
        [q[a], q[a + 1], q[a + 2], q[a + 3]]
    }
}

/// Runs `f` with the model holding `params` (token `token`) and the state:
/// the robot's own copy, or this thread's working copy of the shared model,
/// with the parameters written in first unless they are there already.
#[inline]
fn run<R>(
    slot: &mut ModelSlot,
    token: u64,
    params: &RobotParams,
    data: &mut Data,
    f: impl FnOnce(&Model, &mut Data) -> Result<R>,
) -> Result<R> {
    let prepare = |model: &mut Model, written: &mut u64| {
        if *written != token {
            params.write_into(model);
            *written = token;
        }
    };
    match slot {
        ModelSlot::Own { model, written } => {
            prepare(model, written);
            f(model, data)
        }
        ModelSlot::Shared(base) => with_worker_model(base, |model, written| {
            prepare(model, written);
            f(model, data)
        }),
    }
}

/// One PD physics step of `d` with `m`.
#[inline]
fn pd_step(
    m: &Model,
    d: &mut Data,
    layout: &RobotLayout,
    control: &ControlConfig,
    strength: &[f64; NUM_JOINTS],
    target_rad: &[f64; NUM_JOINTS],
) -> Result<[f64; NUM_JOINTS]> {
    let q = layout.joint_pos(d.qpos());
    let qd = layout.joint_vel(d.qvel());
    let tau = control.pd_torques_scaled(target_rad, &q, &qd, strength);
    let ctrl = d.ctrl_mut();
    for (i, &t) in tau.iter().enumerate() {
        ctrl[layout.actuator_ids[i]] = t;
    }
    d.step(m)?;
    Ok(tau)
}

/// A thread's working copy of a shared model, and the params token last
/// written into it.
struct WorkerModel {
    base: Weak<Model>,
    model: Model,
    written: u64,
}

thread_local! {
    /// One working copy per shared model per thread (VecEnv's workers, or the
    /// thread that steps a lone env). Copies of dropped models are freed on
    /// this thread's next use, and all of them when the thread ends.
    static WORKER_MODELS: RefCell<Vec<WorkerModel>> = const { RefCell::new(Vec::new()) };
}

/// Runs `f` with this thread's working copy of `base` (made on first use). The
/// copy is taken out of the thread's list during `f`, so a nested call cannot
/// alias it (it would make a second copy).
fn with_worker_model<R>(
    base: &Arc<Model>,
    f: impl FnOnce(&mut Model, &mut u64) -> Result<R>,
) -> Result<R> {
    let found = WORKER_MODELS.with(|w| {
        let mut w = w.borrow_mut();
        let i = w
            .iter()
            .position(|e| std::ptr::eq(e.base.as_ptr(), Arc::as_ptr(base)))?;
        Some(w.swap_remove(i))
    });
    let mut entry = match found {
        Some(e) => e,
        None => {
            WORKER_MODELS.with(|w| w.borrow_mut().retain(|e| e.base.strong_count() > 0));
            WorkerModel {
                base: Arc::downgrade(base),
                model: base.try_clone()?,
                written: 0,
            }
        }
    };
    let out = f(&mut entry.model, &mut entry.written);
    WORKER_MODELS.with(|w| w.borrow_mut().push(entry));
    out
}
