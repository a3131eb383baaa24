//! Which checkpoint is a run's final policy, by a rule written in the experiment
//! file (`[selection]`): among the checkpoints of the run's last `window` iterations
//! (every `every`), the one that falls least on validation episodes, a seed the
//! tracking table does not use; a tie goes to the later checkpoint. Without
//! `[selection]` the final policy is the last checkpoint. RMA's teacher is chosen
//! by the same rule among phase 1's last checkpoints, before phase 2 starts.
//!
//! Why (docs/research-log.md): with the scalar critic a checkpoint's fall
//! rate swings between 0% and 11% from one checkpoint to the next, 50 iterations
//! apart, so the last one alone is a draw.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use serde::{Deserialize, Serialize};

use crate::runner::RunDir;

/// The chosen checkpoint, beside the run's `latest.safetensors`.
pub const SELECTED: &str = "selected.safetensors";
/// Every candidate's validation figures and which was chosen.
pub const SELECTION_CSV: &str = "selection.csv";
/// RMA: the same for its teacher, chosen among phase 1's checkpoints before phase 2.
pub const TEACHER_SELECTION_CSV: &str = "teacher-selection.csv";

/// What a rule chooses: a run's final policy, or RMA's teacher between its phases
/// (the same rule, so that RMA's teacher is not the one draw of the campaign that
/// nobody chose: the student can only be as good as the teacher it imitates).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Choice {
    FinalPolicy,
    Teacher,
}

impl Choice {
    fn csv(self) -> &'static str {
        match self {
            Choice::FinalPolicy => SELECTION_CSV,
            Choice::Teacher => TEACHER_SELECTION_CSV,
        }
    }
    fn what(self) -> &'static str {
        match self {
            Choice::FinalPolicy => "final policy",
            Choice::Teacher => "RMA teacher (phase 1, before phase 2 starts)",
        }
    }
}

/// `[selection]` of the experiment file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SelectionSpec {
    /// Candidates: the checkpoints of the last `window` iterations of the budget ...
    pub window: usize,
    /// ... at every `every`-th iteration (the runs' save interval or a multiple of it).
    pub every: usize,
    /// Validation episodes per candidate (`rall eval tracking`, mean actions).
    pub episodes: usize,
    /// Validation seed; must differ from `[tracking] seed`.
    pub seed: u64,
}

/// One candidate's validation result.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Candidate {
    pub iteration: usize,
    pub fall_rate: f64,
    pub lin_vel_score: f64,
    pub yaw_rate_score: f64,
}

impl SelectionSpec {
    pub fn validate(&self, tracking_seed: u64) -> Result<()> {
        if self.window == 0 || self.every == 0 || self.episodes == 0 {
            bail!("selection: window, every and episodes must be at least 1");
        }
        if self.seed == tracking_seed {
            bail!(
                "selection.seed is {} like tracking.seed: the final policy must be chosen on other episodes than those it is judged on",
                self.seed
            );
        }
        Ok(())
    }

    /// Candidate iterations of a run whose budget (with RMA's phase 2) is `target`,
    /// oldest first; the last iteration is always one.
    pub fn candidates(&self, target: usize) -> Vec<usize> {
        let first = target.saturating_sub(self.window) + 1;
        (first..=target)
            .filter(|&it| it % self.every == 0 || it == target)
            .collect()
    }

    /// First line of `selection.csv`: a stored choice is reused only under the same rule.
    fn header(&self, target: usize, choice: Choice) -> String {
        format!(
            "# {}: fewest falls over {} validation episodes (seed {}) among the checkpoints of iterations {}-{} every {}",
            choice.what(),
            self.episodes,
            self.seed,
            target.saturating_sub(self.window) + 1,
            target,
            self.every
        )
    }
}

/// Index of the candidate with the fewest falls; a tie goes to the later one.
pub fn choose(c: &[Candidate]) -> Option<usize> {
    (0..c.len()).min_by(|&a, &b| c[a].fall_rate.total_cmp(&c[b].fall_rate).then(b.cmp(&a)))
}

/// The checkpoint file of iteration `it` in run directory `dir` (a final policy's
/// last candidate may be `latest` alone; a teacher's never: `latest` is where the
/// chosen teacher is installed).
pub fn checkpoint_of(dir: &Path, it: usize, target: usize, choice: Choice) -> Option<PathBuf> {
    let rd = RunDir {
        root: dir.to_path_buf(),
    };
    let numbered = rd.checkpoint(it);
    if numbered.exists() {
        return Some(numbered);
    }
    (choice == Choice::FinalPolicy && it == target && rd.latest().exists()).then(|| rd.latest())
}

/// The iteration chosen in `dir`'s stored choice, if it was made under this rule
/// and budget.
fn stored_iteration(
    dir: &Path,
    spec: &SelectionSpec,
    target: usize,
    choice: Choice,
) -> Option<usize> {
    let text = std::fs::read_to_string(dir.join(choice.csv())).ok()?;
    let mut lines = text.lines();
    if lines.next() != Some(spec.header(target, choice).as_str()) {
        return None;
    }
    // the row whose `chosen` column is 1
    lines
        .skip(1)
        .find(|l| l.ends_with(",1"))?
        .split(',')
        .next()?
        .parse()
        .ok()
}

/// The stored choice in `dir` (its file and iteration), if it was made under this
/// rule and budget.
pub fn stored(dir: &Path, spec: &SelectionSpec, target: usize) -> Option<(PathBuf, usize)> {
    let iteration = stored_iteration(dir, spec, target, Choice::FinalPolicy)?;
    let selected = dir.join(SELECTED);
    selected.exists().then_some((selected, iteration))
}

/// The stored teacher choice of the RMA run in `dir` whose phase 1 ends at
/// `phase1_end`, if it was made under this rule.
pub fn stored_teacher(dir: &Path, spec: &SelectionSpec, phase1_end: usize) -> Option<usize> {
    stored_iteration(dir, spec, phase1_end, Choice::Teacher)
}

/// Chooses run `dir`'s final policy (`validate` tracks one checkpoint on the
/// validation episodes), writes `selection.csv` and `selected.safetensors` (both
/// atomically) and returns the chosen candidate.
pub fn select(
    dir: &Path,
    spec: &SelectionSpec,
    target: usize,
    validate: impl FnMut(&Path) -> Result<Candidate>,
) -> Result<Candidate> {
    select_as(dir, spec, target, Choice::FinalPolicy, validate)
}

/// [`select`] for a final policy or (`Choice::Teacher`, `target` = the end of
/// phase 1) an RMA teacher, which writes `teacher-selection.csv` alone: the chosen
/// teacher is installed into the run ([`crate::runner::install_teacher`]).
pub fn select_as(
    dir: &Path,
    spec: &SelectionSpec,
    target: usize,
    choice: Choice,
    mut validate: impl FnMut(&Path) -> Result<Candidate>,
) -> Result<Candidate> {
    let its = spec.candidates(target);
    let paths = its
        .iter()
        .map(|&it| {
            checkpoint_of(dir, it, target, choice).with_context(|| {
                format!(
                    "choosing the {} of {}: it has no checkpoint of iteration {it} (the rule takes iterations {}-{target} every {}; runs save every runner.save_interval)",
                    choice.what(),
                    dir.display(),
                    its[0],
                    spec.every
                )
            })
        })
        .collect::<Result<Vec<_>>>()?;
    let mut found = Vec::with_capacity(paths.len());
    for (&it, path) in its.iter().zip(&paths) {
        let c = validate(path)?;
        found.push(Candidate { iteration: it, ..c });
    }
    let k = choose(&found).context("no candidates")?;
    let mut csv = spec.header(target, choice);
    csv.push_str("\niteration,fall_pct,lin_tracking,yaw_tracking,chosen\n");
    for (i, c) in found.iter().enumerate() {
        let _ = writeln!(
            csv,
            "{},{:.2},{:.4},{:.4},{}",
            c.iteration,
            100.0 * c.fall_rate,
            c.lin_vel_score,
            c.yaw_rate_score,
            u8::from(i == k)
        );
    }
    if choice == Choice::FinalPolicy {
        crate::fsio::copy_atomic(&paths[k], &dir.join(SELECTED))?;
    }
    crate::fsio::write_atomic(&dir.join(choice.csv()), csv.as_bytes())?;
    Ok(found[k])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_selection_files_are_run_entries() {
        // a new run refuses folders with files rall did not write: these are rall's
        for f in [SELECTED, SELECTION_CSV, TEACHER_SELECTION_CSV] {
            assert!(crate::runner::run_dir::RUN_ENTRIES.contains(&f), "{f}");
        }
    }

    fn cand(iteration: usize, fall_rate: f64) -> Candidate {
        Candidate {
            iteration,
            fall_rate,
            lin_vel_score: 0.9,
            yaw_rate_score: 0.8,
        }
    }

    #[test]
    fn candidates_are_the_window_every_k_and_the_last_iteration() {
        let s = SelectionSpec {
            window: 500,
            every: 50,
            episodes: 256,
            seed: 4242,
        };
        let c = s.candidates(4500);
        assert_eq!(c.len(), 10);
        assert_eq!((c[0], c[9]), (4050, 4500));
        // a budget off the grid still has its last iteration
        assert_eq!(s.candidates(120), vec![50, 100, 120]);
    }

    #[test]
    fn the_fewest_falls_win_and_a_tie_goes_to_the_later_checkpoint() {
        let c = [
            cand(50, 0.02),
            cand(100, 0.0),
            cand(150, 0.05),
            cand(200, 0.0),
        ];
        assert_eq!(choose(&c), Some(3));
        assert_eq!(choose(&c[..3]), Some(1));
        assert_eq!(choose(&[]), None);
    }

    #[test]
    fn choosing_on_the_tracking_seed_is_refused() {
        let s = SelectionSpec {
            window: 100,
            every: 50,
            episodes: 8,
            seed: 777,
        };
        let e = s.validate(777).unwrap_err().to_string();
        assert!(e.contains("other episodes"), "{e}");
        s.validate(778).unwrap();
    }
}
