//! [`ObsLayout`]: the observation row as named column blocks ("groups"). The
//! env decides what a group holds; the learner only reads columns by name.

use std::ops::Range;

use anyhow::{bail, Result};

/// Group names and widths, in row order.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ObsLayout {
    groups: Vec<(String, usize)>,
}

impl ObsLayout {
    pub fn from_groups(groups: Vec<(String, usize)>) -> ObsLayout {
        ObsLayout { groups }
    }

    /// One group named "policy" of `width` values (checkpoints made before groups existed).
    pub fn policy_only(width: usize) -> ObsLayout {
        ObsLayout::from_groups(vec![("policy".into(), width)])
    }

    pub fn groups(&self) -> &[(String, usize)] {
        &self.groups
    }

    /// Values in one row.
    pub fn width(&self) -> usize {
        self.groups.iter().map(|g| g.1).sum()
    }

    /// Columns of group `name`, if present.
    pub fn range(&self, name: &str) -> Option<Range<usize>> {
        let mut at = 0;
        for (g, w) in &self.groups {
            if g == name {
                return Some(at..at + w);
            }
            at += w;
        }
        None
    }

    /// Columns of group `name`, or an error naming it and what the row has.
    pub fn require(&self, name: &str, wanted_by: &str) -> Result<Range<usize>> {
        match self.range(name) {
            Some(r) => Ok(r),
            None => bail!(
                "{wanted_by} reads observation group {name:?}, but the env writes only [{}] (add it to env.observation.groups)",
                self.names().join(", ")
            ),
        }
    }

    pub fn names(&self) -> Vec<&str> {
        self.groups.iter().map(|g| g.0.as_str()).collect()
    }

    /// `policy:48,privileged:31`, as stored in checkpoints.
    pub fn to_meta(&self) -> String {
        self.groups
            .iter()
            .map(|(n, w)| format!("{n}:{w}"))
            .collect::<Vec<_>>()
            .join(",")
    }

    /// Inverse of [`ObsLayout::to_meta`].
    pub fn parse_meta(text: &str) -> Result<ObsLayout> {
        let mut groups = Vec::new();
        for part in text.split(',') {
            let Some((name, width)) = part.split_once(':') else {
                bail!("observation groups {text:?}: {part:?} is not name:width");
            };
            let Ok(width) = width.parse::<usize>() else {
                bail!("observation groups {text:?}: width of {name:?} is not a number");
            };
            groups.push((name.to_string(), width));
        }
        Ok(ObsLayout { groups })
    }

    /// Refuses `other` (what this build makes of the same config) unless every
    /// group has the same name, width and place, naming the first that differs.
    pub fn check_same(&self, other: &ObsLayout, what: &str) -> Result<()> {
        for (i, (name, width)) in self.groups.iter().enumerate() {
            match other.groups.get(i) {
                Some((n, w)) if n == name && w == width => {}
                Some((n, w)) if n == name => bail!(
                    "{what}: observation group {name:?} is {width} values wide in the checkpoint but {w} in this build"
                ),
                Some((n, _)) => bail!(
                    "{what}: observation group {} is {name:?} in the checkpoint but {n:?} in this build",
                    i + 1
                ),
                None => bail!(
                    "{what}: observation group {name:?} is in the checkpoint but not produced by this build"
                ),
            }
        }
        if let Some((n, _)) = other.groups.get(self.groups.len()) {
            bail!("{what}: observation group {n:?} is produced by this build but missing from the checkpoint");
        }
        Ok(())
    }
}

/// Copies the columns `ranges` of each of `rows` rows of `x` (`rows x width`)
/// into `out` (`rows x sum(ranges)`), in the order given.
pub fn gather_columns(x: &[f32], width: usize, ranges: &[Range<usize>], out: &mut Vec<f32>) {
    let rows = x.len().checked_div(width).unwrap_or(0);
    let w: usize = ranges.iter().map(|r| r.len()).sum();
    out.clear();
    out.reserve(rows * w);
    for row in x.chunks_exact(width) {
        for r in ranges {
            out.extend_from_slice(&row[r.clone()]);
        }
    }
}
