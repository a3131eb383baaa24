//! A plain snapshot of the robot, computed once per policy step: everything the
//! observation, the reward and the risk terms read. No MuJoCo types.

use nalgebra::{Quaternion, UnitQuaternion, Vector3};

use crate::robot::NUM_JOINTS;

#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct RobotState {
    /// Base linear velocity in the body frame (m/s).
    pub base_lin_vel_body_mps: [f64; 3],
    /// Base angular velocity in the body frame (rad/s).
    pub base_ang_vel_body_rad_s: [f64; 3],
    /// Unit gravity direction in the body frame ((0, 0, -1) when level).
    pub gravity_body: [f64; 3],
    pub roll_rad: f64,
    pub pitch_rad: f64,
    /// Joint angles (rad), SDK order.
    pub q_rad: [f64; NUM_JOINTS],
    /// Joint velocities (rad/s).
    pub qd_rad_s: [f64; NUM_JOINTS],
    /// Joint accelerations (rad/s^2): finite difference of qd over the policy step.
    pub qdd_rad_s2: [f64; NUM_JOINTS],
    /// Torques applied in the last physics step (N m).
    pub torques_nm: [f64; NUM_JOINTS],
    /// Foot touching anything outside the robot, per leg.
    pub foot_contact: [bool; 4],
    /// Thigh, calf and trunk geoms touching anything outside the robot.
    pub penalised_contacts: usize,
    /// The trunk touches the ground (a geom of the world body).
    pub trunk_on_ground: bool,
}

/// MuJoCo's (w, x, y, z) quaternion as nalgebra's unit quaternion (MuJoCo keeps
/// it normalised; it is not renormalised here).
#[inline]
pub fn unit_quat(q: [f64; 4]) -> UnitQuaternion<f64> {
    UnitQuaternion::new_unchecked(Quaternion::new(q[0], q[1], q[2], q[3]))
}

/// v expressed in the frame rotated by unit quaternion q (w, x, y, z): R(q)^T v.
#[inline]
pub fn rotate_inverse(q: [f64; 4], v: [f64; 3]) -> [f64; 3] {
    unit_quat(q)
        .inverse_transform_vector(&Vector3::from(v))
        .into()
}

/// v rotated by unit quaternion q (w, x, y, z): R(q) v.
#[inline]
pub fn rotate(q: [f64; 4], v: [f64; 3]) -> [f64; 3] {
    unit_quat(q).transform_vector(&Vector3::from(v)).into()
}

/// (roll, pitch, yaw) in rad of unit quaternion q (w, x, y, z), ZYX convention.
#[inline]
pub fn roll_pitch_yaw(q: [f64; 4]) -> [f64; 3] {
    let (roll, pitch, yaw) = unit_quat(q).euler_angles();
    [roll, pitch, yaw]
}
