//! Per-iteration metrics: aggregated from finished episodes and the update,
//! appended to `metrics.csv`.

use std::fs::{File, OpenOptions};
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};

use crate::env::reward::{NUM_REWARD_TERMS, REWARD_TERM_NAMES};
use crate::env::risk::{NUM_RISK_TERMS, RISK_TERM_NAMES};
use crate::env::{EpisodeEnd, EpisodeSummary};
use crate::learn::UpdateStats;

/// The fields of columns `names` in every row of a `metrics.csv` whose text is
/// `text` (read from `path`, which errors name); a field a short row lacks is
/// empty, and a column the header lacks is an error naming it.
pub fn metrics_columns<'a, const N: usize>(
    text: &'a str,
    path: &Path,
    names: [&str; N],
) -> Result<Vec<[&'a str; N]>> {
    let mut lines = text.lines();
    let head: Vec<&str> = lines.next().unwrap_or("").split(',').collect();
    let mut cols = [0; N];
    for (c, name) in cols.iter_mut().zip(names) {
        *c = head
            .iter()
            .position(|h| *h == name)
            .with_context(|| format!("{} has no column {name}", path.display()))?;
    }
    Ok(lines
        .map(|line| {
            let f: Vec<&str> = line.split(',').collect();
            cols.map(|c| f.get(c).copied().unwrap_or(""))
        })
        .collect())
}

/// Means over the episodes that finished in one iteration.
#[derive(Debug, Clone, Default)]
pub struct EpisodeStats {
    pub episodes: usize,
    pub mean_return: f64,
    pub mean_length_steps: f64,
    /// Mean per-step linear-velocity tracking score exp(-err^2/sigma) in [0, 1].
    pub lin_tracking_score: f64,
    pub falls: usize,
    pub reward_terms: [f64; NUM_REWARD_TERMS],
    /// Risk firings within 1 s before those episodes' falls, summed.
    pub risk_fired_before_fall: [u64; NUM_RISK_TERMS],
}

impl EpisodeStats {
    /// `lin_weight_dt` = lin_vel_tracking weight x policy dt (to undo the scaling).
    pub fn from_episodes(eps: &[EpisodeSummary], lin_weight_dt: f64) -> EpisodeStats {
        let mut s = EpisodeStats {
            episodes: eps.len(),
            ..Default::default()
        };
        if eps.is_empty() {
            return s;
        }
        let n = eps.len() as f64;
        let mut tracking_sum = 0.0;
        let mut steps = 0.0;
        for e in eps {
            s.mean_return += e.total_reward / n;
            s.mean_length_steps += e.steps as f64 / n;
            tracking_sum += e.reward_terms[0];
            steps += e.steps as f64;
            s.falls += (e.end != EpisodeEnd::TimeOut) as usize;
            for (t, v) in s.reward_terms.iter_mut().zip(&e.reward_terms) {
                *t += v / n;
            }
            for (t, v) in s
                .risk_fired_before_fall
                .iter_mut()
                .zip(&e.risk_fired_before_fall)
            {
                *t += *v as u64;
            }
        }
        if steps > 0.0 && lin_weight_dt != 0.0 {
            s.lin_tracking_score = tracking_sum / lin_weight_dt / steps;
        }
        s
    }

    /// Sums that add across ranks: `[n, n x return, n x length, tracking x steps,
    /// falls, n x term...]` (see [`Self::from_sums`]).
    pub fn sums(&self) -> Vec<f64> {
        let n = self.episodes as f64;
        let steps = n * self.mean_length_steps;
        let mut v = vec![
            n,
            n * self.mean_return,
            steps,
            self.lin_tracking_score * steps,
            self.falls as f64,
        ];
        v.extend(self.reward_terms.iter().map(|t| n * t));
        v.extend(self.risk_fired_before_fall.iter().map(|&c| c as f64));
        v
    }

    /// The statistics of the episodes behind several ranks' summed [`Self::sums`].
    pub fn from_sums(v: &[f64]) -> EpisodeStats {
        let mut s = EpisodeStats {
            episodes: v[0].round() as usize,
            falls: v[4].round() as usize,
            ..Default::default()
        };
        if v[0] > 0.0 {
            s.mean_return = v[1] / v[0];
            s.mean_length_steps = v[2] / v[0];
            for (t, x) in s.reward_terms.iter_mut().zip(&v[5..]) {
                *t = x / v[0];
            }
        }
        let before = &v[(5 + NUM_REWARD_TERMS).min(v.len())..];
        for (c, x) in s.risk_fired_before_fall.iter_mut().zip(before) {
            *c = x.round() as u64;
        }
        if v[2] > 0.0 {
            s.lin_tracking_score = v[3] / v[2];
        }
        s
    }
}

/// Where the collection's wall time went (seconds per iteration).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct CollectTimes {
    /// PD control and `mj_step` (share of the parallel env pass).
    pub physics_s: f64,
    /// Observation, reward, risk, pushes (share of the parallel env pass).
    pub task_s: f64,
    /// Counters, curriculum and auto-resets.
    pub reset_s: f64,
    /// Policy forward passes and action sampling.
    pub inference_s: f64,
    /// Rollout storage and everything else.
    pub storage_s: f64,
}

/// One CSV row.
pub struct IterationRow<'a> {
    pub iteration: usize,
    pub wall_s: f64,
    pub total_env_steps: u64,
    /// Env steps collected in this iteration.
    pub iteration_env_steps: u64,
    pub collect_s: f64,
    pub learn_s: f64,
    pub collect_times: CollectTimes,
    pub episodes: &'a EpisodeStats,
    pub update: &'a UpdateStats,
    pub terrain_level: f64,
    pub risk_exceeded: &'a [u64; NUM_RISK_TERMS],
    pub risk_fired: &'a [u64; NUM_RISK_TERMS],
    /// This iteration's firings within 1 s before a fall.
    pub risk_fired_before_fall: &'a [u64; NUM_RISK_TERMS],
    pub instabilities: u64,
    /// Processes training the policy (MPI ranks; 1 alone).
    pub ranks: usize,
}

/// Columns appended after the risk counters: gradient norms and where the
/// iteration's time went (seconds).
const TIMING_COLUMNS: [&str; 19] = [
    "actor_grad_norm",
    "critic_grad_norm",
    "clipped_fraction",
    "learning_rate_mean",
    "learning_rate_max",
    "collect_physics_s",
    "collect_task_s",
    "collect_reset_s",
    "collect_inference_s",
    "collect_storage_s",
    "learn_targets_s",
    "learn_gather_s",
    "learn_forward_s",
    "learn_loss_s",
    "learn_backward_s",
    "learn_clip_s",
    "learn_adam_s",
    "learn_comm_s",
    "ranks",
];

/// For each column of `new_head`, its index in `old_head` (by name).
fn column_map(old_head: &str, new_head: &str) -> Vec<Option<usize>> {
    let old: Vec<&str> = old_head.split(',').collect();
    new_head
        .split(',')
        .map(|c| old.iter().position(|o| *o == c))
        .collect()
}

/// A metrics file open for appending: each row is appended whole or not at
/// all ([`crate::fsio::append_whole`]), and errors name the file's full path.
pub struct MetricsCsv {
    out: File,
    path: PathBuf,
}

fn header() -> String {
    let mut cols: Vec<String> = [
        "iteration",
        "wall_s",
        "total_env_steps",
        "collect_s",
        "learn_s",
        "env_steps_per_s",
        "episodes",
        "mean_return",
        "mean_episode_length",
        "lin_tracking_score",
        "fall_fraction",
        "terrain_level",
        "policy_loss",
        "value_loss",
        "entropy",
        "approx_kl",
        "learning_rate",
        "mean_std",
        "clip_fraction",
        "grad_norm",
        "instabilities",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    cols.extend(REWARD_TERM_NAMES.iter().map(|n| format!("rew_{n}")));
    cols.extend(RISK_TERM_NAMES.iter().map(|n| format!("risk_exceeded_{n}")));
    cols.extend(RISK_TERM_NAMES.iter().map(|n| format!("risk_fired_{n}")));
    cols.extend(TIMING_COLUMNS.iter().map(|n| n.to_string()));
    cols.extend(
        RISK_TERM_NAMES
            .iter()
            .map(|n| format!("risk_fired_before_fall_{n}")),
    );
    cols.join(",")
}

impl MetricsCsv {
    /// Opens the metrics of a run resumed at `iteration`: rows after it (written
    /// after the checkpoint the run resumes from) and a row cut short by a full
    /// disk or a kill are dropped; rows written by an older rall (other columns)
    /// are carried over by column name, columns they lack left empty; all
    /// atomically (temp file + rename), then the file is opened for appending.
    pub fn open_resumed(path: &Path, iteration: usize) -> Result<MetricsCsv> {
        Self::open_resumed_with(path, iteration, &header())
    }

    /// [`MetricsCsv::open_resumed`] of a file with columns `head` (its first column
    /// the iteration).
    pub fn open_resumed_with(path: &Path, iteration: usize, head: &str) -> Result<MetricsCsv> {
        if path.exists() {
            let text = std::fs::read_to_string(path)
                .with_context(|| format!("reading {}", path.display()))?;
            let mut kept = String::with_capacity(text.len());
            kept.push_str(head);
            kept.push('\n');
            // only complete lines (a cut last line has no newline)
            let complete = text.rsplit_once('\n').map_or("", |(c, _)| c);
            let mut lines = complete.lines();
            let old_head = lines.next().unwrap_or(head);
            let map = column_map(old_head, head);
            let old_width = old_head.split(',').count();
            for line in lines {
                let fields: Vec<&str> = line.split(',').collect();
                let it = fields.first().and_then(|v| v.parse::<usize>().ok());
                if fields.len() != old_width || it.is_none_or(|it| it > iteration) {
                    continue;
                }
                let row: Vec<&str> = map.iter().map(|m| m.map_or("", |k| fields[k])).collect();
                kept.push_str(&row.join(","));
                kept.push('\n');
            }
            crate::fsio::write_atomic(path, kept.as_bytes())?;
        }
        Self::open_with(path, head)
    }

    /// Opens `path` for appending (a resumed run keeps its history), writing the header if new.
    pub fn open(path: &Path) -> Result<MetricsCsv> {
        Self::open_with(path, &header())
    }

    fn open_with(path: &Path, head: &str) -> Result<MetricsCsv> {
        let is_new = !path.exists()
            || std::fs::metadata(path)
                .map(|m| m.len() == 0)
                .unwrap_or(true);
        let out = OpenOptions::new()
            .create(true)
            .append(true)
            .open(path)
            .with_context(|| format!("opening {}", path.display()))?;
        let mut csv = MetricsCsv {
            out,
            path: path.to_path_buf(),
        };
        if is_new {
            csv.write_line(head)?;
        }
        Ok(csv)
    }

    /// Appends one already formatted row (and its newline) whole, or nothing.
    pub fn write_line(&mut self, row: &str) -> Result<()> {
        let line = format!("{row}\n");
        crate::fsio::append_whole(&mut self.out, &self.path, line.as_bytes())
    }

    pub fn write(&mut self, r: &IterationRow) -> Result<()> {
        let e = r.episodes;
        let u = r.update;
        let elapsed = r.collect_s + r.learn_s;
        let steps_per_s = if elapsed > 0.0 {
            r.iteration_env_steps as f64 / elapsed
        } else {
            0.0
        };
        let mut row = format!(
            "{},{:.3},{},{:.4},{:.4},{:.1},{},{:.5},{:.2},{:.5},{:.4},{:.3},{:.6},{:.6},{:.5},{:.6},{:.3e},{:.5},{:.4},{:.4},{}",
            r.iteration,
            r.wall_s,
            r.total_env_steps,
            r.collect_s,
            r.learn_s,
            steps_per_s,
            e.episodes,
            e.mean_return,
            e.mean_length_steps,
            e.lin_tracking_score,
            if e.episodes > 0 { e.falls as f64 / e.episodes as f64 } else { 0.0 },
            r.terrain_level,
            u.policy_loss,
            u.value_loss,
            u.entropy,
            u.approx_kl,
            u.learning_rate,
            u.mean_std,
            u.clip_fraction,
            u.grad_norm,
            r.instabilities,
        );
        for t in &e.reward_terms {
            row.push_str(&format!(",{t:.6}"));
        }
        for v in r.risk_exceeded.iter().chain(r.risk_fired) {
            row.push_str(&format!(",{v}"));
        }
        let (c, t) = (&r.collect_times, &u.time);
        row.push_str(&format!(
            ",{:.4},{:.4},{:.4},{:.3e},{:.3e}",
            u.actor_grad_norm,
            u.critic_grad_norm,
            u.clipped_fraction,
            u.learning_rate_mean,
            u.learning_rate_max
        ));
        for v in [
            c.physics_s,
            c.task_s,
            c.reset_s,
            c.inference_s,
            c.storage_s,
            t.targets_s,
            t.gather_s,
            t.forward_s,
            t.loss_s,
            t.backward_s,
            t.clip_s,
            t.adam_s,
            t.comm_s,
        ] {
            row.push_str(&format!(",{v:.4}"));
        }
        row.push_str(&format!(",{}", r.ranks));
        for v in r.risk_fired_before_fall {
            row.push_str(&format!(",{v}"));
        }
        self.write_line(&row)
    }
}
