//! The results README: every table as Markdown, the paper's numbers beside ours.

use std::fmt::Write as _;

use super::{write_ttf_table, ExperimentResults, TrackingEstimates};
use crate::experiment::contrasts::contrasts_markdown;
use crate::experiment::curve_plots::CURVE_FIGURES;
use crate::experiment::curves::{curve_markdown, CurvePoint};
use crate::experiment::pooled::show_with_seeds;
use crate::experiment::stats::Estimate;

impl ExperimentResults {
    fn spread_markdown(&self, s: &mut String) {
        if self.checkpoint_spread.is_empty() {
            return;
        }
        let _ = writeln!(s, "## From checkpoint to checkpoint\n");
        let _ = writeln!(s, "Every run's number in tables I and II is the mean over its last checkpoints (below, newest first), each judged on its share of the robots; this is how much a single checkpoint would have moved it. The race and the tracking judge each run's `[selection]` policy (a secondary view).\n");
        let _ = writeln!(
            s,
            "| benchmark | run | checkpoints | per checkpoint | min - max |"
        );
        let _ = writeln!(s, "|---|---|---|---|---|");
        for c in &self.checkpoint_spread {
            let digits = if c.benchmark == "ttf" { 3 } else { 1 };
            let its: Vec<String> = c.iterations.iter().map(|i| i.to_string()).collect();
            let vals: Vec<String> = c.values.iter().map(|v| format!("{v:.digits$}")).collect();
            let _ = writeln!(
                s,
                "| {} | {} | {} | {} | {:.digits$} - {:.digits$} |",
                c.benchmark,
                c.run,
                its.join(", "),
                vals.join(", "),
                c.min(),
                c.max()
            );
        }
        let _ = writeln!(s);
    }

    fn curves_markdown(&self, s: &mut String) {
        let Some(ladder) = &self.ladder else { return };
        if self.curves.is_empty() {
            return;
        }
        let mut rungs: Vec<usize> = self.curves.iter().map(|p| p.severity).collect();
        rungs.sort_unstable();
        rungs.dedup();
        let _ = writeln!(
            s,
            "## Robustness curves
"
        );
        let braces = if self.curves.iter().any(|p| !p.seeds.is_empty()) {
            ", each training seed's own number in braces"
        } else {
            ""
        };
        let _ = writeln!(s, "Each method (seeds pooled with equal weight) on every rung of the severity ladder; rung 0 is the paper's protocol (the tables below), each higher rung harder on every axis. 95% bootstrap over robots in brackets{braces}; `figures/curve_<benchmark>.svg` draws them, `curves.csv` lists them.
");
        let _ = writeln!(s, "{}", ladder.markdown(&rungs));
        for (metric, title, digits) in [
            ("ttf", "Time to Fall, mean over table I's cells", 3),
            ("strict_ttf", "Time to Fall, strict fall definition", 3),
            (
                "success_pct",
                "Platform success (%), the rung's heights pooled",
                1,
            ),
            ("return_q25", "Race return, 0.25 quantile", 1),
        ] {
            let these: Vec<CurvePoint> = self
                .curves
                .iter()
                .filter(|p| p.metric == metric)
                .cloned()
                .collect();
            if these.is_empty() {
                continue;
            }
            let _ = writeln!(s, "### {title}\n\n{}", curve_markdown(&these, digits));
            if let Some(f) = CURVE_FIGURES.iter().find(|f| f.1 == metric) {
                let _ = writeln!(s, "![{}](figures/curve_{}.svg)\n", f.2, f.0);
            }
        }
        let _ = writeln!(s, "{}\n", crate::eval::FALL_DEFINITION);
    }

    /// Methods in table order (first appearance).
    fn methods_of<'a>(names: impl Iterator<Item = &'a String>) -> Vec<String> {
        let mut out: Vec<String> = Vec::new();
        for n in names {
            if !out.contains(n) {
                out.push(n.clone());
            }
        }
        out
    }

    pub fn markdown(&self) -> String {
        let mut s = String::new();
        let _ = writeln!(s, "# Results: {}\n", self.name);
        if let Some(v) = &self.verdicts {
            v.markdown(&mut s);
        }
        if let Some(p) = &self.preface {
            let _ = writeln!(s, "{}\n", p.trim_end());
        }
        self.benchmarks.markdown(&mut s);
        let _ = writeln!(
            s,
            "Every number: ours with its {} in brackets; the paper's beside it where it gives one.\n",
            self.confidence
        );
        contrasts_markdown(&self.contrasts, &mut s);
        self.runs_markdown(&mut s);
        self.common_ground_markdown(&mut s);

        self.curves_markdown(&mut s);
        self.spread_markdown(&mut s);
        crate::experiment::risk_signal::risk_markdown(&self.risk_signal, &mut s);
        crate::experiment::critic_tail::tail_markdown(self.critic_tail.as_ref(), &mut s);
        self.methods_markdown(&mut s);
        self.per_run_markdown(&mut s);
        let _ = writeln!(s, "\n## Figures\n");
        for f in crate::experiment::plots::figures(self) {
            let (f, what) = (f.file_name(), f.shows());
            let _ = writeln!(s, "- [{f}](figures/{f}): {what}");
        }
        s
    }

    /// The training runs: budget, progress and tracking of each.
    fn runs_markdown(&self, s: &mut String) {
        let _ = writeln!(s, "## Training runs\n");
        let _ = writeln!(
            s,
            "| Method | iterations | env steps | wall clock (h) | terrain level | lin tracking | yaw tracking | falls |"
        );
        let _ = writeln!(s, "|---|---:|---:|---:|---:|---:|---:|---:|");
        for r in &self.runs {
            let unfinished = if r.iterations_done == 0 {
                " (not started)"
            } else if r.iterations_done < r.iterations_target {
                " (unfinished)"
            } else {
                ""
            };
            let chosen = r
                .policy_iteration
                .map_or(String::new(), |it| format!(", policy of {it}"));
            let [lin, yaw, falls] = r
                .tracking
                .map_or_else(|| ["-".to_string(), "-".into(), "-".into()], |t| t.cells());
            let _ = writeln!(
                s,
                "| {} | {} / {}{unfinished}{chosen} | {:.1} M | {:.2} | {} | {lin} | {yaw} | {falls} |",
                r.label,
                r.iterations_done,
                r.iterations_target,
                r.env_steps as f64 / 1e6,
                r.wall_clock_h,
                r.terrain_level.map_or("-".into(), |l| format!("{l:.2}")),
            );
        }
        let _ = writeln!(s, "\nTracking: `rall eval tracking` protocol ({} episodes, mean actions, flat ground, each policy under its own training randomisation); targets: linear >= 0.8, yaw >= 0.7, falls < 5%.",
            self.runs.first().map_or(0, |r| r.tracking_episodes));
        let _ = writeln!(s);
    }

    /// Every run on its own: tables I and II, the race and the meta controllers.
    fn per_run_markdown(&self, s: &mut String) {
        let _ = writeln!(s, "## Per training run\n");
        let _ = writeln!(
            s,
            "Every run on its own (the tables above pool these by method).\n"
        );
        let loads = Self::methods_of(self.ttf.iter().map(|r| &r.load));
        let methods = Self::methods_of(self.ttf.iter().map(|r| &r.method));
        write_ttf_table(
            s,
            &loads,
            &methods,
            |_, m| Some(m.to_string()),
            |l, m, (t, p)| {
                let c = self
                    .ttf
                    .iter()
                    .find(|r| r.load == l && r.method == m && r.terrain == t && r.push == p)?;
                let paper = c
                    .paper
                    .map_or(String::new(), |p| format!(" (paper {p:.3})"));
                Some(format!("{}{paper}", c.ttf.show(3)))
            },
        );
        let _ = writeln!(s, "\n### Table II: walking off a platform (success %)\n");
        let _ = writeln!(s, "| Height | Method | ours | paper | robots |");
        let _ = writeln!(s, "|---:|---|---:|---:|---:|");
        for r in &self.platform {
            let _ = writeln!(
                s,
                "| {:.2} m | {} | {} | {} | {} |",
                r.height_m,
                r.method,
                r.success_pct.show(1),
                r.paper.map_or("-".into(), |p| format!("{p:.1}")),
                r.robots
            );
        }
        let _ = writeln!(s, "\n### Race track: return quantiles\n");
        let _ = writeln!(
            s,
            "| Method | q0.25 (worst case) | q0.5 | q0.75 (best case) | mean | falls | episodes |"
        );
        let _ = writeln!(s, "|---|---:|---:|---:|---:|---:|---:|");
        for r in &self.race {
            let _ = writeln!(
                s,
                "| {} | {} | {} | {} | {:.2} | {:.1}% | {} |",
                r.method,
                r.q25.show(2),
                r.q50.show(2),
                r.q75.show(2),
                r.mean_return,
                100.0 * r.fall_fraction,
                r.episodes
            );
        }
        for m in &self.meta {
            let _ = writeln!(
                s,
                "\nMeta controller {}: {} (risk neutral) / {} (risk averse); {}: {:.4}. On the race it acted with {} for {:.1}% of robot-steps, {:.2} switches per episode.",
                m.label,
                m.risky,
                m.safe,
                m.rule,
                m.threshold,
                m.safe,
                100.0 * m.safe_fraction,
                m.switches_per_episode
            );
        }
        let _ = writeln!(s, "\nThe paper gives the race only as a figure (fig. 4, right): the meta controller has the highest return at all three quantiles.");
    }

    /// The paper's TTF for `method` at `load` and column `k`.
    fn paper_ttf(&self, method: &str, load: &str, (t, p): (&str, bool)) -> Option<f64> {
        self.ttf
            .iter()
            .find(|r| r.method == method && r.load == load && r.terrain == t && r.push == p)
            .and_then(|r| r.paper)
    }

    /// The three tables with one row per method (seeds pooled, each seed in braces).
    fn methods_markdown(&self, s: &mut String) {
        let m = &self.methods;
        if m.ttf.is_empty() && m.platform.is_empty() && m.race.is_empty() {
            return;
        }
        let _ = writeln!(s, "## Each method over its training seeds\n");
        let _ = writeln!(s, "Runs that differ only in their training seed are one method here. Its number weights every seed equally (the mean of the seeds' means; the race: quantiles of the seeds' returns pooled) with a 95% bootstrap that resamples robots within each seed; each seed's own value follows in braces, because with two or three seeds the spread between them is the honest measure of what another seed would do, and no interval over robots covers it.\n");
        let loads = Self::methods_of(m.ttf.iter().map(|r| &r.load));
        let labels = Self::methods_of(m.ttf.iter().map(|r| &r.method.label));
        write_ttf_table(
            s,
            &loads,
            &labels,
            |l, label| {
                m.ttf
                    .iter()
                    .find(|r| r.load == l && r.method.label == label)
                    .map(|r| r.method.display())
            },
            |l, label, (t, p)| {
                let c = m.ttf.iter().find(|r| {
                    r.load == l && r.method.label == label && r.terrain == t && r.push == p
                })?;
                let paper = self
                    .paper_ttf(label, l, (t, p))
                    .map_or(String::new(), |p| format!(" (paper {p:.3})"));
                Some(format!(
                    "{}{paper}",
                    show_with_seeds(&c.ttf, &c.per_seed, 3)
                ))
            },
        );
        let _ = writeln!(s, "\n### Table II: walking off a platform (success %)\n");
        let _ = writeln!(s, "| Height | Method | ours | paper | robots |");
        let _ = writeln!(s, "|---:|---|---:|---:|---:|");
        for r in &m.platform {
            let paper = self
                .platform
                .iter()
                .find(|p| p.method == r.method.label && p.height_m == r.height_m)
                .and_then(|p| p.paper);
            let _ = writeln!(
                s,
                "| {:.2} m | {} | {} | {} | {} |",
                r.height_m,
                r.method.display(),
                show_with_seeds(&r.success_pct, &r.per_seed, 1),
                paper.map_or("-".into(), |p| format!("{p:.1}")),
                r.robots
            );
        }
        let _ = writeln!(s, "\n### Race track: return quantiles\n");
        let _ = writeln!(
            s,
            "| Method | q0.25 (worst case) | q0.5 | q0.75 (best case) | falls | episodes |"
        );
        let _ = writeln!(s, "|---|---:|---:|---:|---:|---:|");
        for r in &m.race {
            let q = |k: usize, e: &Estimate| {
                let seeds: Vec<f64> = r.per_seed.iter().map(|q| q[k]).collect();
                show_with_seeds(e, &seeds, 2)
            };
            let _ = writeln!(
                s,
                "| {} | {} | {} | {} | {:.1}% | {} |",
                r.method.display(),
                q(0, &r.q25),
                q(1, &r.q50),
                q(2, &r.q75),
                100.0 * r.fall_fraction,
                r.episodes
            );
        }
        let _ = writeln!(s);
    }

    /// Tracking with every policy on the same ground: one column per common
    /// randomisation, beside each policy's own.
    fn common_ground_markdown(&self, s: &mut String) {
        if self.common_randomization.is_empty() {
            return;
        }
        let _ = writeln!(s, "### Tracking on common ground: lin / yaw / falls\n");
        let _ = write!(s, "| Method | own randomisation |");
        for c in &self.common_randomization {
            let _ = write!(s, " `{c}`'s |");
        }
        let _ = writeln!(
            s,
            "\n|---|---:|{}",
            "---:|".repeat(self.common_randomization.len())
        );
        let show = |t: Option<&TrackingEstimates>| t.map_or("-".into(), |t| t.cells().join(" / "));
        for r in &self.runs {
            let _ = write!(s, "| {} | {} |", r.label, show(r.tracking.as_ref()));
            for k in 0..self.common_randomization.len() {
                let _ = write!(s, " {} |", show(r.common_tracking.get(k)));
            }
            let _ = writeln!(s);
        }
        let _ = writeln!(s, "\nThe same episodes (commands, noise, starts) with friction, added mass, motor strength, PD factors and centre of mass drawn from each config's `[env.randomization]` for every policy (`rall eval tracking --randomization-from CONFIG`, pushes off), so that all methods walk on the same ground; the targets above apply to the own column.\n");
    }
}
