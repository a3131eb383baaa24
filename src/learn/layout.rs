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

/// Rows of `x` laid out as `from`, re-laid out as `to` (each of `to`'s groups
/// taken from `from` by name): how two policies with different groups read one
/// env (the meta controller with an RMA student).
pub fn relayout_rows(x: &[f32], from: &ObsLayout, to: &ObsLayout) -> Result<Vec<f32>> {
    if from == to {
        return Ok(x.to_vec());
    }
    let mut ranges = Vec::with_capacity(to.groups.len());
    for (name, width) in &to.groups {
        let r = from.require(name, "a policy")?;
        if r.len() != *width {
            bail!(
                "observation group {name:?} is {} values wide in the env but {width} in the policy",
                r.len()
            );
        }
        ranges.push(r);
    }
    let mut out = Vec::new();
    gather_columns(x, from.width(), &ranges, &mut out);
    Ok(out)
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

#[cfg(test)]
mod tests {
    use super::*;

    fn layout(text: &str) -> ObsLayout {
        ObsLayout::parse_meta(text).unwrap()
    }

    #[test]
    fn rows_are_relaid_out_by_group_name() {
        let env = layout("policy:2,privileged:1,history:3");
        let x: Vec<f32> = (0..12).map(|v| v as f32).collect(); // two rows
        let student = layout("policy:2,history:3");
        assert_eq!(
            relayout_rows(&x, &env, &student).unwrap(),
            vec![0.0, 1.0, 3.0, 4.0, 5.0, 6.0, 7.0, 9.0, 10.0, 11.0]
        );
        assert_eq!(relayout_rows(&x, &env, &env).unwrap(), x);
        let e = relayout_rows(&x, &layout("policy:2"), &student).unwrap_err();
        assert!(format!("{e}").contains("\"history\""), "{e}");
        let e = relayout_rows(&x, &env, &layout("policy:2,history:4")).unwrap_err();
        assert!(
            format!("{e}").contains("history") && format!("{e}").contains("wide"),
            "{e}"
        );
    }

    #[test]
    fn layouts_compare_group_by_group() {
        let a = layout("policy:48,privileged:31");
        assert!(a.check_same(&a.clone(), "x").is_ok());
        let e = a
            .check_same(&layout("policy:48,privileged:30"), "x")
            .unwrap_err();
        assert!(format!("{e}").contains("\"privileged\""), "{e}");
        let e = a.check_same(&layout("policy:48"), "x").unwrap_err();
        assert!(format!("{e}").contains("\"privileged\""), "{e}");
        assert!(ObsLayout::parse_meta("policy").is_err());
        assert_eq!(a.range("privileged"), Some(48..79));
        assert_eq!(ObsLayout::parse_meta(&a.to_meta()).unwrap(), a);
    }
}
