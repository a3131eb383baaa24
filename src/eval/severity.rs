//! The severity ladder: rung 0 is the paper's protocol, each higher rung makes
//! every perturbation of a benchmark harder (push force and period, rough-ground
//! amplitude, arm swings, ball travel, platform height, race obstacles). The
//! ladder is data: `experiments/severity-ladder.toml` is built in, and a file
//! with the same keys replaces it (`--ladder`).

use std::path::Path;

use anyhow::{bail, Context, Result};
use serde::{Deserialize, Serialize};

use super::scenario::ScenarioParams;

/// The built-in ladder's text.
pub const BUILTIN_LADDER_TOML: &str = include_str!("../../experiments/severity-ladder.toml");

/// One rung: every axis, all required (a ladder file missing one is refused).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Rung {
    pub push_force_n: f64,
    pub push_every_steps: usize,
    pub rough_amplitude_m: f64,
    pub arm_resample_s: f64,
    pub ball_container_scale: f64,
    pub platform_heights_m: Vec<f64>,
    pub race_obstacle_height_m: f64,
    pub race_drop_height_m: f64,
    pub race_rough_amplitude_m: f64,
    /// The race course's own pushes: the TTF pushes of the same rung end nearly every
    /// race episode at its first push from rung 2 on, so the race climbs more gently.
    pub race_push_force_n: f64,
    pub race_push_every_steps: usize,
    /// Ground friction, uniform in [lo, hi] per robot.
    pub friction: [f64; 2],
    /// Mass added to the trunk (kg), uniform in [lo, hi] per robot.
    pub added_base_mass_kg: [f64; 2],
}

/// The rungs, in order of severity.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Ladder {
    #[serde(rename = "rung")]
    pub rungs: Vec<Rung>,
}

impl Rung {
    fn validate(&self, index: usize) -> Result<()> {
        let positive = [
            ("push_force_n", self.push_force_n),
            ("rough_amplitude_m", self.rough_amplitude_m),
            ("arm_resample_s", self.arm_resample_s),
            ("ball_container_scale", self.ball_container_scale),
            ("race_obstacle_height_m", self.race_obstacle_height_m),
            ("race_drop_height_m", self.race_drop_height_m),
            ("race_rough_amplitude_m", self.race_rough_amplitude_m),
            ("race_push_force_n", self.race_push_force_n),
        ];
        for (key, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                bail!("severity rung {index}: {key} = {v} must be finite and > 0");
            }
        }
        let hold = ScenarioParams::default().push_hold_steps;
        for (key, every) in [
            ("push_every_steps", self.push_every_steps),
            ("race_push_every_steps", self.race_push_every_steps),
        ] {
            if every <= hold {
                bail!(
                    "severity rung {index}: {key} = {every} must exceed the push's {hold} held steps"
                );
            }
        }
        if !(0.5..=3.0).contains(&self.ball_container_scale) {
            bail!(
                "severity rung {index}: ball_container_scale = {} is outside [0.5, 3] (the container must stay on the trunk)",
                self.ball_container_scale
            );
        }
        let [f0, f1] = self.friction;
        if !(f0.is_finite() && f1.is_finite() && 0.0 < f0 && f0 <= f1) {
            bail!("severity rung {index}: friction = [{f0}, {f1}] must be a range of positive numbers");
        }
        let [m0, m1] = self.added_base_mass_kg;
        if !(m0.is_finite() && m1.is_finite() && m0 <= m1 && m0 > -5.0 && m1 < 20.0) {
            bail!("severity rung {index}: added_base_mass_kg = [{m0}, {m1}] must be a range within (-5, 20) kg");
        }
        if self.platform_heights_m.is_empty() {
            bail!("severity rung {index}: platform_heights_m is empty");
        }
        for &h in &self.platform_heights_m {
            if !(h.is_finite() && h > 0.0 && h < 2.0) {
                bail!("severity rung {index}: platform height {h} m is not in (0, 2)");
            }
        }
        Ok(())
    }

    /// `base` with this rung's axes of the TTF and platform benchmarks (the axes
    /// the rung does not set stay).
    pub fn apply(&self, base: &ScenarioParams) -> ScenarioParams {
        let mut p = base.clone();
        p.push_force_n = self.push_force_n;
        p.push_every_steps = self.push_every_steps;
        p.rough.amplitude_m = self.rough_amplitude_m;
        p.arm_resample_s = self.arm_resample_s;
        p.ball_container_scale = self.ball_container_scale;
        // `--no-randomization` (None) stays off
        if p.friction.is_some() {
            p.friction = Some(self.friction);
        }
        if p.added_base_mass_kg.is_some() {
            p.added_base_mass_kg = Some(self.added_base_mass_kg);
        }
        p
    }

    /// `base` with this rung's race axes: the course and the race's own pushes.
    /// Friction and added mass stay `base`'s (the paper's ranges): the course and the
    /// pushes alone already take the race from few falls to nearly all.
    pub fn apply_race(&self, base: &ScenarioParams) -> ScenarioParams {
        let mut p = base.clone();
        p.push_force_n = self.race_push_force_n;
        p.push_every_steps = self.race_push_every_steps;
        p.race.obstacle_height_m = self.race_obstacle_height_m;
        p.race.drop_height_m = self.race_drop_height_m;
        p.race.rough_amplitude_m = self.race_rough_amplitude_m;
        p
    }
}

impl Ladder {
    /// The built-in ladder.
    pub fn builtin() -> Ladder {
        Ladder::from_toml_str(BUILTIN_LADDER_TOML, "the built-in ladder")
            .expect("the built-in severity ladder parses")
    }

    /// A ladder file (every key in every rung), checked.
    pub fn from_toml_file(path: &Path) -> Result<Ladder> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("reading the severity ladder {}", path.display()))?;
        Ladder::from_toml_str(&text, &path.display().to_string())
    }

    pub fn from_toml_str(text: &str, what: &str) -> Result<Ladder> {
        let ladder: Ladder = toml::from_str(text)
            .with_context(|| format!("severity ladder {what} (every rung needs every axis)"))?;
        if ladder.rungs.is_empty() {
            bail!("severity ladder {what} has no [[rung]]");
        }
        for (i, r) in ladder.rungs.iter().enumerate() {
            r.validate(i)
                .with_context(|| format!("severity ladder {what}"))?;
        }
        Ok(ladder)
    }

    /// The rung of severity `s`, or an error naming the ladder's range.
    pub fn rung(&self, s: usize) -> Result<&Rung> {
        self.rungs.get(s).with_context(|| {
            format!(
                "severity {s} is not on the ladder (rungs 0..={})",
                self.rungs.len() - 1
            )
        })
    }

    /// Parses `--severity 0,1,2,3` (each on the ladder, no repeats).
    pub fn parse_list(&self, list: &str) -> Result<Vec<usize>> {
        let mut out = Vec::new();
        for word in list.split(',').map(str::trim).filter(|w| !w.is_empty()) {
            let s: usize = word
                .parse()
                .with_context(|| format!("--severity {list:?}: {word:?} is not a rung number"))?;
            self.rung(s)?;
            if out.contains(&s) {
                bail!("--severity {list:?}: rung {s} is given twice");
            }
            out.push(s);
        }
        if out.is_empty() {
            bail!("--severity {list:?}: no rung given");
        }
        Ok(out)
    }

    /// The ladder as a markdown table (printed with every result).
    pub fn markdown(&self, rungs: &[usize]) -> String {
        let mut s = String::from(
            "| rung | push | rough ground | friction | added mass | arm targets every | ball container | platform | race blocks / drop / rough | race push |\n|---:|---|---|---|---|---|---|---|---|---|\n",
        );
        for &i in rungs {
            let r = &self.rungs[i];
            let heights: Vec<String> = r
                .platform_heights_m
                .iter()
                .map(|h| format!("{h:.2}"))
                .collect();
            s.push_str(&format!(
                "| {i} | {:.0} N every {} steps | +-{:.3} m | {:.2}-{:.2} | {:.1} to {:.1} kg | {:.1} s | x{:.2} | {} m | {:.2} / {:.2} / {:.2} m | {:.0} N every {} steps |\n",
                r.push_force_n,
                r.push_every_steps,
                r.rough_amplitude_m,
                r.friction[0],
                r.friction[1],
                r.added_base_mass_kg[0],
                r.added_base_mass_kg[1],
                r.arm_resample_s,
                r.ball_container_scale,
                heights.join(", "),
                r.race_obstacle_height_m,
                r.race_drop_height_m,
                r.race_rough_amplitude_m,
                r.race_push_force_n,
                r.race_push_every_steps
            ));
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rung_zero_is_the_paper_protocol() {
        let l = Ladder::builtin();
        assert!(l.rungs.len() >= 4);
        let d = ScenarioParams::default();
        assert_eq!(l.rungs[0].apply(&d), d);
        assert_eq!(l.rungs[0].apply_race(&d), d);
        assert_eq!(l.rungs[0].platform_heights_m, vec![0.40, 0.45]);
    }

    #[test]
    fn every_rung_is_at_least_as_hard_as_the_one_below() {
        let l = Ladder::builtin();
        for w in l.rungs.windows(2) {
            let (a, b) = (&w[0], &w[1]);
            assert!(b.push_force_n >= a.push_force_n);
            assert!(b.push_every_steps <= a.push_every_steps);
            assert!(b.rough_amplitude_m >= a.rough_amplitude_m);
            assert!(b.arm_resample_s <= a.arm_resample_s);
            assert!(b.ball_container_scale >= a.ball_container_scale);
            let top = |r: &Rung| r.platform_heights_m.iter().cloned().fold(0.0, f64::max);
            assert!(top(b) >= top(a));
            assert!(b.race_obstacle_height_m >= a.race_obstacle_height_m);
            assert!(b.race_drop_height_m >= a.race_drop_height_m);
            assert!(b.race_rough_amplitude_m >= a.race_rough_amplitude_m);
            assert!(b.race_push_force_n >= a.race_push_force_n);
            assert!(b.race_push_every_steps <= a.race_push_every_steps);
            assert!(b.friction[0] <= a.friction[0] && b.friction[1] <= a.friction[1]);
            assert!(b.added_base_mass_kg[1] >= a.added_base_mass_kg[1]);
        }
    }

    #[test]
    fn bad_ladders_and_severities_are_named() {
        let l = Ladder::builtin();
        let e = format!("{:#}", l.parse_list("0,9").unwrap_err());
        assert!(e.contains("severity 9") && e.contains("rungs 0..="), "{e}");
        assert!(l.parse_list("0,0").is_err());
        assert!(l.parse_list("x").is_err());
        assert_eq!(l.parse_list("0, 2").unwrap(), vec![0, 2]);
        let missing = BUILTIN_LADDER_TOML.replacen("rough_amplitude_m = 0.05\n", "", 1);
        let e = format!("{:#}", Ladder::from_toml_str(&missing, "t").unwrap_err());
        assert!(e.contains("rough_amplitude_m"), "{e}");
        let bad = BUILTIN_LADDER_TOML.replacen("push_force_n = 100.0", "push_force_n = -1.0", 1);
        let e = format!("{:#}", Ladder::from_toml_str(&bad, "t").unwrap_err());
        assert!(e.contains("push_force_n"), "{e}");
        assert!(Ladder::from_toml_str("", "t").is_err());
    }
}
