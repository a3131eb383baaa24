//! The `privileged` observation group: what a teacher policy may know and the
//! robot cannot measure (RMA's environment factors e_t, plus the push in effect,
//! the true base velocity and the ground under the feet).

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
pub const PRIVILEGED_DIM: usize = {
    let mut n = 0;
    let mut i = 0;
    while i < PRIVILEGED_FIELDS.len() {
        n += PRIVILEGED_FIELDS[i].1;
        i += 1;
    }
    n
};

/// `name:width*scale@offset,...`, stored in checkpoints.
pub fn layout_string() -> String {
    PRIVILEGED_FIELDS
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

    /// Writes the scaled group into `out` (length [`PRIVILEGED_DIM`]).
    pub fn write(&self, out: &mut [f32]) {
        let v = self.values();
        let mut i = 0;
        for (_, width, offset, scale) in PRIVILEGED_FIELDS {
            for _ in 0..width {
                out[i] = ((v[i] - offset) * scale) as f32;
                i += 1;
            }
        }
    }
}
