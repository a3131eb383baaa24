//! `rall calibrate-risk`: risk thresholds from the gait's own rare tail. Robots
//! walk in a checkpoint's training env (terrain at its stored curriculum levels,
//! pushes, randomisation, sampled actions as in training); per joint, the chosen
//! quantile of |joint velocity|, |joint acceleration| and |torque| becomes that
//! joint's threshold, so a penalty marks what the walking gait rarely does.

use anyhow::{ensure, Result};
use rand::SeedableRng;

use crate::config::TrainConfig;
use crate::env::risk::RISK_TERMS;
use crate::learn::Learner;
use crate::robot::NUM_JOINTS;
use crate::stats::quantile;

/// The joint terms calibrated, by their names in [`RISK_TERMS`].
pub const CALIBRATED_TERMS: [&str; 3] = ["joint_velocity", "joint_acceleration", "joint_torque"];

/// Per-joint thresholds of the joint terms, and how often today's thresholds
/// are crossed on the same states.
#[derive(Debug, Clone, PartialEq)]
pub struct RiskCalibration {
    pub quantile: f64,
    pub robots: usize,
    pub steps: usize,
    /// Robot-steps measured (falls excluded: the state after a reset is not gait).
    pub states: usize,
    /// Per term of [`CALIBRATED_TERMS`]: the quantile of |x| per joint.
    pub per_joint: [[f64; NUM_JOINTS]; 3],
    /// Per term of [`RISK_TERMS`]: the share of robot-steps crossing the config's
    /// thresholds (before calibration).
    pub crossed_before: [f64; RISK_TERMS.len()],
    /// Per term of [`CALIBRATED_TERMS`]: the share of robot-steps in which any joint
    /// crosses its calibrated threshold.
    pub crossed_after: [f64; 3],
    /// Joints whose torque quantile reached the torque limit: their threshold is set
    /// to [`SATURATION_FRACTION`] of the limit (a saturated motor is the rare event).
    pub saturated_joints: Vec<usize>,
}

/// A torque threshold at the motor's limit could never be crossed (torques are
/// clipped there): such joints get this fraction of their limit instead.
pub const SATURATION_FRACTION: f64 = 0.98;

/// Runs `robots` robots for `steps` steps and measures the joint quantities.
pub fn calibrate_risk(
    learner: &Learner,
    cfg: &TrainConfig,
    terrain_levels: Option<&[usize]>,
    (robots, steps): (usize, usize),
    q: f64,
    threads: usize,
    seed: u64,
) -> Result<RiskCalibration> {
    ensure!(
        q > 0.0 && q < 1.0,
        "--quantile {q} must be in (0, 1), e.g. 0.999"
    );
    ensure!(
        robots > 0 && steps > 0,
        "--robots and --steps must be at least 1"
    );
    let mut envs = super::falls::training_envs(cfg, terrain_levels, robots, threads, seed)?;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let mut obs = envs.batch().obs.clone();
    let mut values: Vec<Vec<Vec<f64>>> = vec![vec![Vec::new(); NUM_JOINTS]; 3];
    let mut crossed = [0usize; RISK_TERMS.len()];
    let mut states = 0;
    for _ in 0..steps {
        let b = envs.step(&learner.act(&obs, &mut rng).actions);
        let dones = b.dones.clone();
        obs.copy_from_slice(&b.obs);
        for (i, env) in envs.envs().iter().enumerate() {
            if dones[i] {
                continue;
            }
            let s = env.state();
            states += 1;
            let crossings = crate::env::risk::risk_crossings(s, &cfg.env.risk);
            for (c, e) in crossed.iter_mut().zip(crossings) {
                *c += e as usize;
            }
            for (k, quantity) in [&s.qd_rad_s, &s.qdd_rad_s2, &s.torques_nm]
                .into_iter()
                .enumerate()
            {
                for (j, x) in quantity.iter().enumerate() {
                    values[k][j].push(x.abs());
                }
            }
        }
    }
    ensure!(
        states > 0,
        "no robot-step to measure: every robot fell at once"
    );
    let mut per_joint: [[f64; NUM_JOINTS]; 3] =
        std::array::from_fn(|k| std::array::from_fn(|j| round_up_3(quantile(&values[k][j], q))));
    let limits = &cfg.env.control.torque_limits_nm;
    let mut saturated_joints = Vec::new();
    for (j, t) in per_joint[2].iter_mut().enumerate() {
        let limit = limits[j % 3];
        if *t >= limit * SATURATION_FRACTION {
            *t = limit * SATURATION_FRACTION;
            saturated_joints.push(j);
        }
    }
    let crossed_after = std::array::from_fn(|k| {
        let any = (0..states)
            .filter(|&n| (0..NUM_JOINTS).any(|j| values[k][j][n] > per_joint[k][j]))
            .count();
        any as f64 / states as f64
    });
    Ok(RiskCalibration {
        quantile: q,
        robots,
        steps,
        states,
        per_joint,
        crossed_before: crossed.map(|c| c as f64 / states as f64),
        crossed_after,
        saturated_joints,
    })
}

impl RiskCalibration {
    /// The `[env.risk.<term>]` tables that set these thresholds, keeping the
    /// config's weights, with a comment saying where they come from.
    pub fn toml_tables(&self, cfg: &TrainConfig, provenance: &str) -> String {
        let mut s = format!(
            "\n# Per-joint risk thresholds: the {} quantile of each joint's |velocity|, |acceleration|\n\
             # and |torque| over {} robot-steps of a walking policy in its training env:\n\
             # {provenance}\n\
             # `threshold` is the largest joint's, for display; `per_joint` decides. Pitch and roll\n\
             # keep the paper's thresholds. Crossed in {} of robot-steps\n\
             # (velocity, acceleration, torque: any joint){}.\n",
            self.quantile,
            self.states,
            self.crossed_after
                .iter()
                .map(|c| format!("{:.2}%", 100.0 * c))
                .collect::<Vec<_>>()
                .join(" / "),
            if self.saturated_joints.is_empty() {
                String::new()
            } else {
                format!(
                    ";\n# torque thresholds of joints {:?} at {} of the motor limit, which their quantile reached",
                    self.saturated_joints, SATURATION_FRACTION
                )
            }
        );
        let terms = cfg.env.risk.terms();
        for (k, name) in CALIBRATED_TERMS.iter().enumerate() {
            let weight = terms
                .iter()
                .find(|(n, _)| n == name)
                .map_or(0.0, |(_, t)| t.weight);
            let per = self.per_joint[k];
            let largest = per.iter().cloned().fold(0.0, f64::max);
            let list: Vec<String> = per.iter().map(|v| format!("{v:?}")).collect();
            s.push_str(&format!(
                "[env.risk.{name}]\nthreshold = {largest:?}\nweight = {weight:?}\nper_joint = [{}]\n",
                list.join(", ")
            ));
        }
        s
    }
}

/// Three significant digits, rounded up (a threshold never below the measured quantile).
fn round_up_3(x: f64) -> f64 {
    if x <= 0.0 || !x.is_finite() {
        return x;
    }
    let scale = 10f64.powi(2 - x.log10().floor() as i32);
    (x * scale).ceil() / scale
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn thresholds_round_up_to_three_digits() {
        assert_eq!(round_up_3(12.341), 12.4);
        assert_eq!(round_up_3(0.0012341), 0.00124);
        assert_eq!(round_up_3(1234.0), 1240.0);
        assert_eq!(round_up_3(5.0), 5.0);
    }
}
