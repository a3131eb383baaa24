#!/usr/bin/env python3
"""Replays the nominal closed-loop trace of a sidecar written by `rall export` with a
control loop built from the sidecar alone: pip MuJoCo for the physics (a newer MuJoCo
than the one rall links), onnxruntime for the network. It checks

  1. the network: onnxruntime on the trace's own observations gives its actions
     (tolerance: the sidecar's reference tolerance);
  2. the control loop: from start_state under the trace's command, the observations,
     actions, joint targets, torques, base velocity and joint angles this loop produces
     stay within TOLERANCES of the trace's, step by step.

The tolerances are set from measurement. With rall's MuJoCo 2.2.2 against pip MuJoCo
4.0.1, the shipped flat RALL policy's 100-step trace differs at most by: obs 8.5e-4,
actions 8.5e-4, joint targets 2.1e-4 rad, torques 1.1e-2 N m, base velocity 7.6e-5 m/s,
base position 7.8e-6 m, joint angles 1.4e-4 rad (the network alone: 8.3e-7). The
tolerances below are about 5x (10x for the base and joint states) those.

usage: python3 tests/check_trace.py OUT.onnx [OUT.json] [--mjcf-root DIR]
"""
import json
import sys
from pathlib import Path

import mujoco
import numpy as np
import onnxruntime as ort

# Largest |difference| allowed per quantity over the trace (units of the quantity).
TOLERANCES = {
    "obs": 5e-3,
    "actions": 5e-3,
    "joint_targets_rad": 1e-3,
    "torques_nm": 5e-2,
    "base_lin_vel_body_mps": 1e-3,
    "base_pos_m": 1e-4,
    "joint_pos_rad": 1e-3,
}


def quat_rotate_inverse(q_wxyz, v):
    """R(q)^T v for a unit quaternion (w, x, y, z)."""
    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, np.asarray(q_wxyz, dtype=np.float64))
    return mat.reshape(3, 3).T @ np.asarray(v, dtype=np.float64)


class Loop:
    """A deployment loop written from the sidecar: observation, network, action law, PD."""

    def __init__(self, side, onnx_path, mjcf_root):
        xml = (mjcf_root / side["robot_mjcf"]).read_text()
        end = xml.rfind("</mujoco>")
        xml = xml[:end] + side["trace"]["conditions"]["ground_xml"] + xml[end:]
        self.m = mujoco.MjModel.from_xml_string(xml)
        self.m.opt.timestep = side["rates"]["physics_dt_s"]
        self.d = mujoco.MjData(self.m)
        key = mujoco.mj_name2id(self.m, mujoco.mjtObj.mjOBJ_KEY, side["joints"]["keyframe"])
        mujoco.mj_resetDataKeyframe(self.m, self.d, key)
        mujoco.mj_forward(self.m, self.d)
        names = side["joints"]["names"]
        jid = [mujoco.mj_name2id(self.m, mujoco.mjtObj.mjOBJ_JOINT, n) for n in names]
        self.qadr = np.array([self.m.jnt_qposadr[j] for j in jid])
        self.vadr = np.array([self.m.jnt_dofadr[j] for j in jid])
        self.act = np.array([mujoco.mj_name2id(self.m, mujoco.mjtObj.mjOBJ_ACTUATOR, n)
                             for n in side["joints"]["mjcf_actuator_names"]])
        self.q0 = np.array(side["joints"]["default_angles_rad_in_order"])
        self.limit = np.array([side["pd"]["torque_limits_nm"][n] for n in names])
        self.kp, self.kd = side["pd"]["kp_nm_per_rad"], side["pd"]["kd_nm_s_per_rad"]
        self.scale, self.clip = side["action"]["scale_rad"], side["action"]["clip"]
        self.decimation = side["rates"]["decimation"]
        self.obs_fields = side["observation"]["fields"]
        self.obs_clip = side["observation"]["clip"]
        self.command = np.array(side["trace"]["conditions"]["command"])
        self.prev_action = np.zeros(len(names), dtype=np.float32)
        self.sess = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])

    def base_lin_vel_body(self):
        return quat_rotate_inverse(self.d.qpos[3:7], self.d.qvel[0:3])

    def observation(self):
        values = {
            "base_lin_vel_body": self.base_lin_vel_body(),
            "base_ang_vel_body": self.d.qvel[3:6],
            "gravity_body": quat_rotate_inverse(self.d.qpos[3:7], [0.0, 0.0, -1.0]),
            "command_vx_vy_yaw": self.command,
            "joint_pos_minus_default": self.d.qpos[self.qadr] - self.q0,
            "joint_vel": self.d.qvel[self.vadr],
            "previous_action": self.prev_action.astype(np.float64),
        }
        parts = [np.asarray(values[f["name"]]) * np.asarray(f["scale"]) for f in self.obs_fields]
        return np.clip(np.concatenate(parts), -self.obs_clip, self.obs_clip).astype(np.float32)

    def policy_step(self, obs):
        action = self.sess.run(["actions"], {"obs": obs[None]})[0][0]
        target = self.q0 + self.scale * np.clip(action.astype(np.float64), -self.clip, self.clip)
        for _ in range(self.decimation):
            q, qd = self.d.qpos[self.qadr], self.d.qvel[self.vadr]
            tau = np.clip(self.kp * (target - q) - self.kd * qd, -self.limit, self.limit)
            self.d.ctrl[self.act] = tau
            mujoco.mj_step(self.m, self.d)
        self.prev_action = action
        return action, target, tau


def replay(side, onnx_path, mjcf_root):
    """Max |difference| per quantity between this loop and the trace."""
    t = side["trace"]
    loop = Loop(side, onnx_path, mjcf_root)
    worst = {k: 0.0 for k in TOLERANCES}
    net = 0.0
    for k in range(t["steps"]):
        obs = loop.observation()
        want_obs = np.asarray(t["obs"][k], dtype=np.float32)
        net_action = loop.sess.run(["actions"], {"obs": want_obs[None]})[0][0]
        net = max(net, float(np.max(np.abs(net_action - np.asarray(t["actions"][k])))))
        action, target, tau = loop.policy_step(obs)
        got = {
            "obs": obs,
            "actions": action,
            "joint_targets_rad": target,
            "torques_nm": tau,
            "base_lin_vel_body_mps": loop.base_lin_vel_body(),
            "base_pos_m": loop.d.qpos[0:3],
            "joint_pos_rad": loop.d.qpos[loop.qadr],
        }
        for key, value in got.items():
            diff = np.max(np.abs(np.asarray(value, dtype=np.float64) - np.asarray(t[key][k])))
            worst[key] = max(worst[key], float(diff))
    return worst, net


def main(argv):
    mjcf_root = Path(__file__).resolve().parent.parent
    if "--mjcf-root" in argv:
        i = argv.index("--mjcf-root")
        mjcf_root = Path(argv[i + 1])
        argv = argv[:i] + argv[i + 2:]
    if len(argv) not in (2, 3):
        print(__doc__, file=sys.stderr)
        return 2
    onnx_path = Path(argv[1])
    side_path = Path(argv[2]) if len(argv) == 3 else onnx_path.with_suffix(".json")
    side = json.loads(side_path.read_text())
    if "trace" not in side:
        print(f"FAIL: {side_path} has no `trace` section", file=sys.stderr)
        return 1
    worst, net = replay(side, onnx_path, mjcf_root)
    tol = float(side["reference"]["tolerance_abs"])
    print(f"mujoco {mujoco.__version__}, onnxruntime {ort.__version__}: "
          f"{side['trace']['steps']} steps of the nominal trace")
    print(f"  network on the trace's observations: max |diff| {net:.2e} (tolerance {tol:.0e})")
    ok = net <= tol
    for key, value in worst.items():
        flag = "ok" if value <= TOLERANCES[key] else "FAIL"
        ok &= value <= TOLERANCES[key]
        print(f"  closed loop {key:<22} max |diff| {value:.2e} (tolerance {TOLERANCES[key]:.0e}) {flag}")
    if not ok:
        print("FAIL: this control loop does not reproduce rall's trace", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
