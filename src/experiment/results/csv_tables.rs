//! The results' CSV tables: every cell with its interval, one file per table.

use std::fmt::Write as _;
use std::path::Path;

use super::{opt, per_seed, seeds, ExperimentResults};
use crate::eval::report::csv_field;
use crate::experiment::contrasts::contrasts_csv;
use crate::experiment::curves::curve_csv;
use crate::experiment::spec::common_ground_name;

impl ExperimentResults {
    /// Every CSV table: (file name, text), the benchmarks' last.
    pub(super) fn csv_files(&self) -> Vec<(String, String)> {
        let mut files = vec![
            ("runs.csv", self.runs_csv()),
            ("ttf_by_method.csv", self.ttf_by_method_csv()),
            ("platform_by_method.csv", self.platform_by_method_csv()),
            ("race_by_method.csv", self.race_by_method_csv()),
            ("ttf.csv", self.ttf_csv()),
            ("platform.csv", self.platform_csv()),
            ("race.csv", self.race_csv()),
        ];
        if !self.curves.is_empty() {
            files.push(("curves.csv", curve_csv(&self.curves)));
        }
        if !self.contrasts.is_empty() {
            files.push(("contrasts.csv", contrasts_csv(&self.contrasts)));
        }
        if let Some(v) = &self.verdicts {
            files.push((
                "verdicts.csv",
                crate::experiment::verdicts::verdicts_csv(&v.rows),
            ));
        }
        if !self.checkpoint_spread.is_empty() {
            files.push(("checkpoints.csv", self.checkpoints_csv()));
        }
        if !self.risk_signal.is_empty() {
            files.push((
                "risk_signal.csv",
                crate::experiment::risk_signal::risk_csv(&self.risk_signal),
            ));
        }
        if let Some(t) = self.critic_tail.as_ref().filter(|t| !t.rows.is_empty()) {
            files.push((
                "critic_tail.csv",
                crate::experiment::critic_tail::tail_csv(t),
            ));
        }
        let mut files: Vec<(String, String)> =
            files.into_iter().map(|(n, t)| (n.to_string(), t)).collect();
        files.extend(self.benchmarks.csv_files());
        files
    }

    /// `runs.csv`: one row per run, its own and its common-ground tracking.
    fn runs_csv(&self) -> String {
        let tracking_columns = |prefix: &str| {
            ["lin_tracking", "yaw_tracking", "fall_rate"]
                .iter()
                .flat_map(|f| {
                    [
                        format!("{prefix}{f}"),
                        format!("{prefix}{f}_lo"),
                        format!("{prefix}{f}_hi"),
                    ]
                })
                .collect::<Vec<_>>()
                .join(",")
        };
        let mut runs = format!(
            "method,config,seed,iterations_done,iterations_target,env_steps,wall_clock_h,terrain_level,{}",
            tracking_columns("")
        );
        // one group of columns per common randomisation, named after its config file
        for c in &self.common_randomization {
            let _ = write!(
                runs,
                ",{}",
                tracking_columns(&format!("on_{}_", common_ground_name(Path::new(c))))
            );
        }
        runs.push('\n');
        let none = ",".repeat(8);
        for r in &self.runs {
            let own = r.tracking.map_or(none.clone(), |t| t.csv());
            let common: String = (0..self.common_randomization.len())
                .map(|k| {
                    format!(
                        ",{}",
                        r.common_tracking.get(k).map_or(none.clone(), |t| t.csv())
                    )
                })
                .collect();
            let _ = writeln!(
                runs,
                "{},{},{},{},{},{},{:.4},{},{own}{common}",
                csv_field(&r.label),
                csv_field(&r.config),
                r.seed,
                r.iterations_done,
                r.iterations_target,
                r.env_steps,
                r.wall_clock_h,
                opt(r.terrain_level),
            );
        }
        runs
    }

    /// `ttf.csv`: time to fall per cell.
    fn ttf_csv(&self) -> String {
        let mut ttf = String::from("method,load,terrain,push,ttf,ttf_lo,ttf_hi,robots,paper\n");
        for r in &self.ttf {
            let _ = writeln!(
                ttf,
                "{},{},{},{},{},{},{}",
                csv_field(&r.method),
                r.load,
                r.terrain,
                r.push,
                r.ttf.csv(4),
                r.robots,
                opt(r.paper)
            );
        }
        ttf
    }

    /// `platform.csv`: platform success per cell.
    fn platform_csv(&self) -> String {
        let mut platform =
            String::from("method,height_m,success_pct,success_lo,success_hi,robots,paper\n");
        for r in &self.platform {
            let _ = writeln!(
                platform,
                "{},{},{},{},{}",
                csv_field(&r.method),
                r.height_m,
                r.success_pct.csv(2),
                r.robots,
                opt(r.paper)
            );
        }
        platform
    }

    /// `race.csv`: race-track return quantiles per policy.
    fn race_csv(&self) -> String {
        let mut race = String::from("method,q25,q25_lo,q25_hi,q50,q50_lo,q50_hi,q75,q75_lo,q75_hi,mean_return,fall_fraction,episodes\n");
        for r in &self.race {
            let _ = writeln!(
                race,
                "{},{},{},{},{:.4},{:.4},{}",
                csv_field(&r.method),
                r.q25.csv(4),
                r.q50.csv(4),
                r.q75.csv(4),
                r.mean_return,
                r.fall_fraction,
                r.episodes
            );
        }
        race
    }

    /// `ttf_by_method.csv`: time to fall pooled over each method's seeds.
    fn ttf_by_method_csv(&self) -> String {
        let mut ttf_m =
            String::from("method,seeds,load,terrain,push,ttf,ttf_lo,ttf_hi,per_seed,robots\n");
        for r in &self.methods.ttf {
            let _ = writeln!(
                ttf_m,
                "{},{},{},{},{},{},{},{}",
                csv_field(&r.method.label),
                seeds(&r.method),
                r.load,
                r.terrain,
                r.push,
                r.ttf.csv(4),
                per_seed(&r.per_seed, 4),
                r.robots
            );
        }
        ttf_m
    }

    /// `platform_by_method.csv`: platform success pooled over seeds.
    fn platform_by_method_csv(&self) -> String {
        let mut platform_m = String::from(
            "method,seeds,height_m,success_pct,success_lo,success_hi,per_seed,robots\n",
        );
        for r in &self.methods.platform {
            let _ = writeln!(
                platform_m,
                "{},{},{},{},{},{}",
                csv_field(&r.method.label),
                seeds(&r.method),
                r.height_m,
                r.success_pct.csv(2),
                per_seed(&r.per_seed, 2),
                r.robots
            );
        }
        platform_m
    }

    /// `race_by_method.csv`: race quantiles pooled over seeds.
    fn race_by_method_csv(&self) -> String {
        let mut race_m = String::from("method,seeds,q25,q25_lo,q25_hi,q50,q50_lo,q50_hi,q75,q75_lo,q75_hi,per_seed_q25,per_seed_q50,per_seed_q75,fall_fraction,episodes\n");
        for r in &self.methods.race {
            let col = |k: usize| per_seed(&r.per_seed.iter().map(|q| q[k]).collect::<Vec<_>>(), 4);
            let _ = writeln!(
                race_m,
                "{},{},{},{},{},{},{},{},{:.4},{}",
                csv_field(&r.method.label),
                seeds(&r.method),
                r.q25.csv(4),
                r.q50.csv(4),
                r.q75.csv(4),
                col(0),
                col(1),
                col(2),
                r.fall_fraction,
                r.episodes
            );
        }
        race_m
    }

    /// `checkpoints.csv`: each benchmark's value at every kept checkpoint.
    fn checkpoints_csv(&self) -> String {
        let mut csv = String::from("benchmark,run,iteration,value\n");
        for c in &self.checkpoint_spread {
            for (it, v) in c.iterations.iter().zip(&c.values) {
                csv.push_str(&format!(
                    "{},{},{it},{v:.4}\n",
                    c.benchmark,
                    csv_field(&c.run)
                ));
            }
        }
        csv
    }
}
