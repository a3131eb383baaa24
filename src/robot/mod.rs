//! The Aliengo on top of the simulation layer: layout, PD control, standing check.

mod layout;
mod pd;
mod standing;

pub use layout::{Part, RobotLayout, LEGS, LEG_JOINTS, NUM_JOINTS};
pub use pd::ControlConfig;
pub use standing::{has_ground, standing_check, with_floor, StandingReport};

use crate::sim::{Data, Model, ObjKind, Result, SimError};

/// One simulated robot: model, state, layout and its PD controller.
pub struct Robot {
    pub model: Model,
    pub data: Data,
    pub layout: RobotLayout,
    pub control: ControlConfig,
    /// Default joint angles (rad) from the control keyframe, SDK order.
    pub default_q_rad: [f64; NUM_JOINTS],
}

impl Robot {
    /// Wraps a loaded model: resolves the layout, applies the physics time step
    /// and resets to the default keyframe.
    pub fn new(mut model: Model, control: ControlConfig) -> Result<Robot> {
        control.validate().map_err(SimError::Invalid)?;
        model.set_timestep_s(control.physics_dt_s);
        let layout = RobotLayout::resolve(&model)?;
        let key = model.require_id(ObjKind::Key, &control.default_keyframe)?;
        let key_qpos = model.key_qpos(key);
        let default_q_rad = std::array::from_fn(|i| key_qpos[layout.qpos_adr[i]]);
        let data = Data::new(&model)?;
        let mut robot = Robot {
            model,
            data,
            layout,
            control,
            default_q_rad,
        };
        robot.reset_to_default()?;
        Ok(robot)
    }

    /// Loads an MJCF file and wraps it.
    pub fn load(path: impl AsRef<std::path::Path>, control: ControlConfig) -> Result<Robot> {
        Robot::new(Model::from_xml_path(path)?, control)
    }

    /// Resets the state to the default keyframe.
    pub fn reset_to_default(&mut self) -> Result<()> {
        let key = self.control.default_keyframe.clone();
        self.data.reset_to_keyframe(&self.model, &key)
    }

    /// One physics step under PD towards `target_rad`; returns the applied torques (N m).
    #[inline]
    pub fn pd_substep(&mut self, target_rad: &[f64; NUM_JOINTS]) -> Result<[f64; NUM_JOINTS]> {
        let q = self.layout.joint_pos(self.data.qpos());
        let qd = self.layout.joint_vel(self.data.qvel());
        let tau = self.control.pd_torques(target_rad, &q, &qd);
        let ctrl = self.data.ctrl_mut();
        for (i, &t) in tau.iter().enumerate() {
            ctrl[self.layout.actuator_ids[i]] = t;
        }
        self.data.step(&self.model)?;
        Ok(tau)
    }

    /// One policy step: `decimation` PD physics steps towards the action's targets.
    pub fn policy_step(&mut self, action: &[f32]) -> Result<[f64; NUM_JOINTS]> {
        let target = self.control.joint_targets(&self.default_q_rad, action);
        let mut tau = [0.0; NUM_JOINTS];
        for _ in 0..self.control.decimation {
            tau = self.pd_substep(&target)?;
        }
        Ok(tau)
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
