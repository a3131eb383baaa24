//! A plain snapshot of the robot, computed once per policy step: everything the
//! observation, the reward and the risk terms read. No MuJoCo types.

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

/// v expressed in the frame rotated by unit quaternion q (w, x, y, z): R(q)^T v.
#[inline]
pub fn rotate_inverse(q: [f64; 4], v: [f64; 3]) -> [f64; 3] {
    let [w, x, y, z] = q;
    let u = [x, y, z];
    let a = 2.0 * w * w - 1.0;
    let cross = [
        u[1] * v[2] - u[2] * v[1],
        u[2] * v[0] - u[0] * v[2],
        u[0] * v[1] - u[1] * v[0],
    ];
    let dot = u[0] * v[0] + u[1] * v[1] + u[2] * v[2];
    std::array::from_fn(|i| v[i] * a - cross[i] * w * 2.0 + u[i] * dot * 2.0)
}

/// v rotated by unit quaternion q (w, x, y, z): R(q) v.
#[inline]
pub fn rotate(q: [f64; 4], v: [f64; 3]) -> [f64; 3] {
    rotate_inverse([q[0], -q[1], -q[2], -q[3]], v)
}

/// (roll, pitch, yaw) in rad of unit quaternion q (w, x, y, z), ZYX convention.
#[inline]
pub fn roll_pitch_yaw(q: [f64; 4]) -> [f64; 3] {
    let [w, x, y, z] = q;
    let roll = (2.0 * (w * x + y * z)).atan2(1.0 - 2.0 * (x * x + y * y));
    let pitch = (2.0 * (w * y - z * x)).clamp(-1.0, 1.0).asin();
    let yaw = (2.0 * (w * z + x * y)).atan2(1.0 - 2.0 * (y * y + z * z));
    [roll, pitch, yaw]
}
