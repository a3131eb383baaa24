//! Where the Aliengo's parts live in a loaded model, resolved once by name.

use crate::sim::{GeomShape, JointKind, Model, ObjKind, Result, SimError};

/// Legs in Unitree SDK order.
pub const LEGS: [&str; 4] = ["FR", "FL", "RR", "RL"];
/// Joints of one leg, in SDK order.
pub const LEG_JOINTS: [&str; 3] = ["hip", "thigh", "calf"];
/// Number of actuated joints.
pub const NUM_JOINTS: usize = 12;

/// Which part of the robot a geom belongs to (for contact classification).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Part {
    Trunk,
    Hip,
    Thigh,
    Calf,
    /// Foot of leg `0..4` in [`LEGS`] order.
    Foot(usize),
    /// Anything else (payloads, arm, terrain).
    Other,
}

/// Indices of the robot's joints, actuators, bodies and geoms in a model.
#[derive(Debug, Clone)]
pub struct RobotLayout {
    /// Joint names in SDK order, e.g. `FR_hip_joint`.
    pub joint_names: Vec<String>,
    pub joint_ids: [usize; NUM_JOINTS],
    pub qpos_adr: [usize; NUM_JOINTS],
    pub dof_adr: [usize; NUM_JOINTS],
    /// Actuator driving joint i (SDK order).
    pub actuator_ids: [usize; NUM_JOINTS],
    pub trunk_body: usize,
    /// qpos address of the free joint (position xyz, then quaternion wxyz).
    pub root_qpos_adr: usize,
    /// qvel address of the free joint (linear world-frame, then angular body-frame).
    pub root_dof_adr: usize,
    pub foot_geoms: [usize; 4],
    /// Part of every geom in the model, indexed by geom id.
    pub geom_parts: Vec<Part>,
}

impl RobotLayout {
    /// Resolves the layout by the naming convention of `mjcf/aliengo.xml`.
    pub fn resolve(model: &Model) -> Result<RobotLayout> {
        let mut joint_names = Vec::with_capacity(NUM_JOINTS);
        let mut joint_ids = [0; NUM_JOINTS];
        let mut qpos_adr = [0; NUM_JOINTS];
        let mut dof_adr = [0; NUM_JOINTS];
        let mut actuator_ids = [0; NUM_JOINTS];
        for (leg_i, leg) in LEGS.iter().enumerate() {
            for (j_i, joint) in LEG_JOINTS.iter().enumerate() {
                let i = leg_i * 3 + j_i;
                let name = format!("{leg}_{joint}_joint");
                let id = model.require_id(ObjKind::Joint, &name)?;
                if model.joint_kind(id) != JointKind::Hinge {
                    return Err(SimError::Invalid(format!("joint {name} must be a hinge")));
                }
                joint_ids[i] = id;
                qpos_adr[i] = model.joint_qpos_adr(id);
                dof_adr[i] = model.joint_dof_adr(id);
                actuator_ids[i] = (0..model.nu())
                    .find(|&a| model.actuator_joint(a) == Some(id))
                    .ok_or_else(|| SimError::Invalid(format!("no actuator drives joint {name}")))?;
                joint_names.push(name);
            }
        }
        let trunk_body = model.require_id(ObjKind::Body, "trunk")?;
        let root = (0..model.njnt())
            .find(|&j| model.joint_kind(j) == JointKind::Free && model.joint_body(j) == trunk_body)
            .ok_or_else(|| SimError::Invalid("the trunk has no free joint".into()))?;
        let mut foot_geoms = [0; 4];
        for (i, leg) in LEGS.iter().enumerate() {
            let g = model.require_id(ObjKind::Geom, &format!("{leg}_foot"))?;
            if model.geom_shape(g) != GeomShape::Sphere {
                return Err(SimError::Invalid(format!(
                    "geom {leg}_foot must be a sphere"
                )));
            }
            foot_geoms[i] = g;
        }
        let geom_parts = (0..model.ngeom())
            .map(|g| classify(model, g, &foot_geoms))
            .collect();
        Ok(RobotLayout {
            joint_names,
            joint_ids,
            qpos_adr,
            dof_adr,
            actuator_ids,
            trunk_body,
            root_qpos_adr: model.joint_qpos_adr(root),
            root_dof_adr: model.joint_dof_adr(root),
            foot_geoms,
            geom_parts,
        })
    }

    /// Joint angles (rad), SDK order.
    pub fn joint_pos(&self, qpos: &[f64]) -> [f64; NUM_JOINTS] {
        std::array::from_fn(|i| qpos[self.qpos_adr[i]])
    }
    /// Joint velocities (rad/s), SDK order.
    pub fn joint_vel(&self, qvel: &[f64]) -> [f64; NUM_JOINTS] {
        std::array::from_fn(|i| qvel[self.dof_adr[i]])
    }
    /// Joint accelerations (rad/s^2), SDK order.
    pub fn joint_acc(&self, qacc: &[f64]) -> [f64; NUM_JOINTS] {
        std::array::from_fn(|i| qacc[self.dof_adr[i]])
    }
    /// Joint ranges (rad), SDK order.
    pub fn joint_ranges(&self, model: &Model) -> [[f64; 2]; NUM_JOINTS] {
        std::array::from_fn(|i| {
            model
                .joint_range(self.joint_ids[i])
                .unwrap_or([f64::NEG_INFINITY, f64::INFINITY])
        })
    }
}

fn classify(model: &Model, geom: usize, feet: &[usize; 4]) -> Part {
    if let Some(leg) = feet.iter().position(|&f| f == geom) {
        return Part::Foot(leg);
    }
    let name = model.name(ObjKind::Geom, geom);
    let body = model.name(ObjKind::Body, model.geom_body(geom));
    for (suffix, part) in [
        ("_hip", Part::Hip),
        ("_thigh", Part::Thigh),
        ("_calf", Part::Calf),
    ] {
        if LEGS.iter().any(|leg| body == format!("{leg}{suffix}")) {
            return part;
        }
    }
    if name == "trunk" || body == "trunk" {
        return Part::Trunk;
    }
    Part::Other
}
