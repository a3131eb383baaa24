//! Writing a results folder: into a staging folder, then each file renamed into
//! place, so a failure leaves what the folder held; `--redraw` from results.json.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};

use super::ExperimentResults;
use crate::experiment::clock::PhaseTime;

impl ExperimentResults {
    /// Writes README.md, the CSVs, results.json and figures/ into `dir`: first all
    /// into a fresh folder beside it, then each file into place by a rename, so a
    /// failure while writing leaves what `dir` held untouched.
    pub fn write(&self, dir: &Path) -> Result<()> {
        let staging = fresh_staging(dir)?;
        self.write_into(&staging)?;
        move_staged(&staging, dir, &["", "figures"])?;
        Ok(())
    }

    /// Writes the README, the CSV tables and the figures of the results already in
    /// `dir` again from its `results.json` with the current code, `preface` opening
    /// the README, without evaluating anything: they are written into a staging
    /// folder, then renamed over the old ones. `results.json` and
    /// `evaluation_time.txt` stay as they are. Returns the files written.
    pub fn redraw(
        dir: &Path,
        preface: Option<String>,
        spec: Option<&crate::experiment::spec::ExperimentSpec>,
    ) -> Result<Vec<PathBuf>> {
        let mut results = ExperimentResults::read(dir)?;
        results.preface = preface;
        if let Some(spec) = spec {
            results.verdicts =
                crate::experiment::verdicts::VerdictsResult::of(spec, &results.contrasts);
        }
        let staging = fresh_staging(dir)?;
        results.write_derived(&staging)?;
        move_staged(&staging, dir, &["", "figures"])
    }

    /// The results stored in `dir`'s `results.json`.
    pub fn read(dir: &Path) -> Result<ExperimentResults> {
        let json = dir.join("results.json");
        let text = std::fs::read_to_string(&json).with_context(|| {
            format!(
                "reading {} (written by `rall experiment`; evaluate first)",
                json.display()
            )
        })?;
        serde_json::from_str(&text)
            .with_context(|| format!("{} is not a results file of this version", json.display()))
    }

    /// The whole evaluation's time, then each phase's: wall-clock minutes and
    /// processor minutes of every thread.
    fn evaluation_time_text(&self) -> String {
        let mut text = self
            .evaluation_time
            .as_ref()
            .map_or("not measured".into(), PhaseTime::show);
        text.push('\n');
        for p in &self.phases {
            text.push_str(&format!("  {}: {}\n", p.phase, p.show()));
        }
        if let Some(r) = &self.rollouts {
            text.push_str(&r.show());
            text.push('\n');
        }
        text
    }

    /// What `results.json` determines, into `dir`: README.md, the CSV tables and
    /// the figures.
    fn write_derived(&self, dir: &Path) -> Result<()> {
        std::fs::create_dir_all(dir.join("figures"))
            .with_context(|| format!("creating {}", dir.display()))?;
        write_file(dir, "README.md", &self.markdown())?;
        let files = self.csv_files();
        for (k, (name, text)) in files.iter().enumerate() {
            anyhow::ensure!(
                !files[..k].iter().any(|(n, _)| n == name),
                "two tables are named {name}: a benchmark's CSV file takes another's name"
            );
            write_file(dir, name, text)?;
        }
        crate::experiment::plots::write_all(self, &dir.join("figures"))
    }

    fn write_into(&self, dir: &Path) -> Result<()> {
        self.write_derived(dir)?;
        write_file(dir, "results.json", &serde_json::to_string_pretty(self)?)?;
        write_file(dir, "evaluation_time.txt", &self.evaluation_time_text())
    }
}

/// Writes `text` to `dir/name`, naming the file on failure.
fn write_file(dir: &Path, name: &str, text: &str) -> Result<()> {
    let path = dir.join(name);
    std::fs::write(&path, text).with_context(|| format!("writing {}", path.display()))
}

/// An empty staging folder beside results folder `dir` (`.<name>.rall-tmp`).
fn fresh_staging(dir: &Path) -> Result<PathBuf> {
    let name = dir
        .file_name()
        .map_or("results".into(), |n| n.to_string_lossy().into_owned());
    let staging = dir.with_file_name(format!(".{name}.rall-tmp"));
    if staging.exists() {
        std::fs::remove_dir_all(&staging)
            .with_context(|| format!("removing {}", staging.display()))?;
    }
    Ok(staging)
}

/// Renames every file of `staging`'s subfolders `subs` ("" is the folder itself)
/// into the same subfolders of `dir`, then removes `staging`; returns the files'
/// new paths, sorted.
fn move_staged(staging: &Path, dir: &Path, subs: &[&str]) -> Result<Vec<PathBuf>> {
    let mut moved = Vec::new();
    for sub in subs {
        std::fs::create_dir_all(dir.join(sub))
            .with_context(|| format!("creating {}", dir.join(sub).display()))?;
        for entry in std::fs::read_dir(staging.join(sub))? {
            let path = entry?.path();
            if path.is_file() {
                let to = dir.join(sub).join(path.file_name().expect("a file name"));
                std::fs::rename(&path, &to)
                    .with_context(|| format!("moving {} to {}", path.display(), to.display()))?;
                moved.push(to);
            }
        }
    }
    std::fs::remove_dir_all(staging).with_context(|| format!("removing {}", staging.display()))?;
    moved.sort();
    Ok(moved)
}

#[cfg(test)]
mod tests {
    use proptest::prelude::*;

    proptest! {
        // --redraw rebuilds every table from results.json: a number read back one unit
        // in the last place off can round to another printed digit
        #[test]
        fn numbers_read_back_from_json_are_the_numbers_written(x in proptest::num::f64::NORMAL) {
            let back: f64 = serde_json::from_str(&serde_json::to_string(&x).unwrap()).unwrap();
            prop_assert_eq!(back.to_bits(), x.to_bits());
        }
    }

    #[test]
    fn a_cell_that_once_moved_reads_back_exactly() {
        let x = 0.970_950_000_000_000_1_f64;
        let back: f64 = serde_json::from_str(&serde_json::to_string(&x).unwrap()).unwrap();
        assert_eq!(format!("{back:.4}"), format!("{x:.4}"));
        assert_eq!(back.to_bits(), x.to_bits());
    }
}
