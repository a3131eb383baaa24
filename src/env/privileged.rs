//! The `privileged` observation group: what a teacher policy may know and the
//! robot cannot measure (RMA's environment factors e_t, plus the push in effect,
//! the true base velocity and the ground under the feet), and the `extrinsics`
//! group: its first fields alone, the episode's randomised factors (RMA's e_t,
//! constant over an episode).

use super::single::EpisodeDraw;
use crate::robot::NUM_JOINTS;

/// (name, width, offset, scale): each value is written as `(v - offset) * scale`,
/// so that every field spans roughly [-1, 1] over its training range.
pub const PRIVILEGED_FIELDS: [(&str, usize, f64, f64); 10] = [
    ("friction", 1, 1.0, 1.0),
    ("added_base_mass_kg", 1, 0.0, 0.2),
    ("com_offset_body_m", 3, 0.0, 10.0),
    ("motor_strength", NUM_JOINTS, 1.0, 5.0),
    ("kp_factor", 1, 1.0, 2.0),
    ("kd_factor", 1, 1.0, 2.0),
    ("push_force_world_n", 3, 0.0, 0.01),
    ("push_kick_world_mps", 2, 0.0, 1.0),
    ("base_lin_vel_body_mps", 3, 0.0, 2.0),
    ("ground_under_feet_minus_base_z_m", 4, -0.4, 2.0),
];

/// Values in the group.
pub const PRIVILEGED_DIM: usize = width_of(PRIVILEGED_FIELDS.len());

/// The `extrinsics` group's fields: the leading [`PRIVILEGED_FIELDS`] up to and
/// including the PD factors (friction, added mass, centre of mass, motor
/// strength, kp, kd: 19 values, the 19-d e_t of RMA's published code), which
/// stay constant over an episode. Not the push, the base velocity or the ground
/// under the feet: those are the robot's state, not its environment.
pub const EXTRINSIC_FIELDS: usize = 6;

/// Values in the `extrinsics` group (a prefix of the `privileged` group's).
pub const EXTRINSICS_DIM: usize = width_of(EXTRINSIC_FIELDS);

const fn width_of(fields: usize) -> usize {
    let mut n = 0;
    let mut i = 0;
    while i < fields {
        n += PRIVILEGED_FIELDS[i].1;
        i += 1;
    }
    n
}

/// `name:width*scale@offset,...`, stored in checkpoints.
pub fn layout_string() -> String {
    fields_string(&PRIVILEGED_FIELDS)
}

/// [`layout_string`] of the `extrinsics` group.
pub fn extrinsics_layout_string() -> String {
    fields_string(&PRIVILEGED_FIELDS[..EXTRINSIC_FIELDS])
}

fn fields_string(fields: &[(&str, usize, f64, f64)]) -> String {
    fields
        .iter()
        .map(|(n, w, o, s)| format!("{n}:{w}*{s}@{o}"))
        .collect::<Vec<_>>()
        .join(",")
}

/// What the group is made of, in physical units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PrivilegedState {
    pub draw: EpisodeDraw,
    /// Force on the trunk during this step (N, world frame; 0 when none).
    pub push_force_world_n: [f64; 3],
    /// Velocity kick applied at the start of this step (m/s, world x y; 0 when none).
    pub push_kick_world_mps: [f64; 2],
    /// True (noise-free) base velocity in the body frame (m/s).
    pub base_lin_vel_body_mps: [f64; 3],
    /// Ground height under each foot minus the trunk height (m), FL FR RL RR.
    pub ground_under_feet_minus_base_z_m: [f64; 4],
}

impl PrivilegedState {
    /// The values in field order, physical units.
    pub fn values(&self) -> [f64; PRIVILEGED_DIM] {
        let d = &self.draw;
        let mut v = [0.0; PRIVILEGED_DIM];
        let mut i = 0;
        let mut put = |xs: &[f64]| {
            v[i..i + xs.len()].copy_from_slice(xs);
            i += xs.len();
        };
        put(&[d.friction.unwrap_or(1.0)]);
        put(&[d.added_base_mass_kg]);
        put(&d.com_offset_m);
        put(&d.motor_strength);
        put(&[d.kp_factor]);
        put(&[d.kd_factor]);
        put(&self.push_force_world_n);
        put(&self.push_kick_world_mps);
        put(&self.base_lin_vel_body_mps);
        put(&self.ground_under_feet_minus_base_z_m);
        v
    }

    /// Writes the scaled `privileged` group into `out` (length [`PRIVILEGED_DIM`]).
    pub fn write(&self, out: &mut [f32]) {
        self.write_leading_fields(PRIVILEGED_FIELDS.len(), out);
    }

    /// Writes the scaled `extrinsics` group, the first [`EXTRINSIC_FIELDS`] of the
    /// `privileged` group, into `out` (length [`EXTRINSICS_DIM`]).
    pub fn write_extrinsics(&self, out: &mut [f32]) {
        self.write_leading_fields(EXTRINSIC_FIELDS, out);
    }

    /// `(v - offset) * scale` for each value of the leading `fields` fields.
    fn write_leading_fields(&self, fields: usize, out: &mut [f32]) {
        assert_eq!(out.len(), width_of(fields), "group width");
        let v = self.values();
        let mut at = 0;
        for &(_, width, offset, scale) in &PRIVILEGED_FIELDS[..fields] {
            for (o, x) in out[at..at + width].iter_mut().zip(&v[at..at + width]) {
                *o = ((x - offset) * scale) as f32;
            }
            at += width;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn extrinsics_are_the_episode_factors_leading_the_privileged_group() {
        assert_eq!(EXTRINSICS_DIM, 19);
        assert_eq!(PRIVILEGED_FIELDS[EXTRINSIC_FIELDS].0, "push_force_world_n");
        let state = PrivilegedState {
            draw: EpisodeDraw {
                friction: Some(1.3),
                added_base_mass_kg: 0.7,
                motor_strength: [0.95; NUM_JOINTS],
                kp_factor: 1.05,
                kd_factor: 0.92,
                com_offset_m: [0.01, -0.02, 0.03],
            },
            push_force_world_n: [50.0, -20.0, 0.0],
            push_kick_world_mps: [0.3, 0.1],
            base_lin_vel_body_mps: [0.5, 0.0, -0.1],
            ground_under_feet_minus_base_z_m: [-0.38; 4],
        };
        let mut full = [0.0f32; PRIVILEGED_DIM];
        let mut ext = [0.0f32; EXTRINSICS_DIM];
        state.write(&mut full);
        state.write_extrinsics(&mut ext);
        assert_eq!(ext[..], full[..EXTRINSICS_DIM]);
        // friction (1.3 - 1) * 1, added mass 0.7 * 0.2, then the centre of mass
        assert!((ext[0] - 0.3).abs() < 1e-6 && (ext[1] - 0.14).abs() < 1e-6);
        assert!((ext[18] - (0.92 - 1.0) * 2.0).abs() < 1e-6);
        assert!(extrinsics_layout_string().ends_with("kd_factor:1*2@1"));
        assert!(layout_string().starts_with(&extrinsics_layout_string()));
    }
}
