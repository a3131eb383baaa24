//! [`RobotParams`]: the model values a robot may change (domain randomisation).

use crate::sim::Model;

/// The model values one robot steps with: written into whichever model it
/// steps with (its own copy, or its thread's copy of a shared model) before
/// each step. Lengths are fixed by the model (slices, never resized).
#[derive(Debug, Clone, PartialEq)]
pub struct RobotParams {
    timestep_s: f64,
    geom_friction: Vec<[f64; 3]>,
    body_mass_kg: Vec<f64>,
    body_subtree_mass_kg: Vec<f64>,
    body_ipos_m: Vec<[f64; 3]>,
}

impl RobotParams {
    /// The values `model` holds now.
    pub fn of(model: &Model) -> RobotParams {
        RobotParams {
            timestep_s: model.timestep_s(),
            geom_friction: model.geom_friction().to_vec(),
            body_mass_kg: model.body_mass_kg().to_vec(),
            body_subtree_mass_kg: model.body_subtree_mass_kg().to_vec(),
            body_ipos_m: model.body_ipos_m().to_vec(),
        }
    }

    /// Writes every value into `model` (one of the family these came from).
    pub fn write_into(&self, model: &mut Model) {
        model.set_timestep_s(self.timestep_s);
        copy(model.geom_friction_mut(), &self.geom_friction);
        copy(model.body_mass_kg_mut(), &self.body_mass_kg);
        copy(model.body_subtree_mass_kg_mut(), &self.body_subtree_mass_kg);
        copy(model.body_ipos_m_mut(), &self.body_ipos_m);
    }

    pub fn timestep_s(&self) -> f64 {
        self.timestep_s
    }
    pub fn set_timestep_s(&mut self, dt_s: f64) {
        self.timestep_s = dt_s;
    }
    /// Sliding, torsional, rolling friction per geom.
    pub fn geom_friction(&self) -> &[[f64; 3]] {
        &self.geom_friction
    }
    pub fn geom_friction_mut(&mut self) -> &mut [[f64; 3]] {
        &mut self.geom_friction
    }
    /// Body masses (kg).
    pub fn body_mass_kg(&self) -> &[f64] {
        &self.body_mass_kg
    }
    pub fn body_mass_kg_mut(&mut self) -> &mut [f64] {
        &mut self.body_mass_kg
    }
    /// Centre of mass of each body in its body frame (m).
    pub fn body_ipos_m(&self) -> &[[f64; 3]] {
        &self.body_ipos_m
    }
    pub fn body_ipos_m_mut(&mut self) -> &mut [[f64; 3]] {
        &mut self.body_ipos_m
    }
    /// Subtree masses (kg); keep them the sums of the body masses below.
    pub fn body_subtree_mass_kg(&self) -> &[f64] {
        &self.body_subtree_mass_kg
    }
    pub fn body_subtree_mass_kg_mut(&mut self) -> &mut [f64] {
        &mut self.body_subtree_mass_kg
    }
}

/// Copies what fits (the lengths agree for models of one family).
fn copy<T: Copy>(dst: &mut [T], src: &[T]) {
    let n = dst.len().min(src.len());
    dst[..n].copy_from_slice(&src[..n]);
}
